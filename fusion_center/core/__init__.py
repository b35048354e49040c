"""The numerical core of the method: pure functions, no CAN, no files, no clock, no plotting."""
