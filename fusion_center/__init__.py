"""taxel-can fusion centre.

The modules at this level that hold numbers only (``encoding``, ``rules``, ``curves``,
``thresholds``, ``baselines``, ``poisson_binomial``, ``forces``, ``geometry``, ``contact``,
``slip``, ``bus_timing``) are the *numerical core*: pure functions, no CAN and no file I/O,
so the same code serves the live bus, replay of a recorded trace and Monte Carlo.
I/O lives in ``scene`` (TOML loading), ``service`` (the CANopen master) and ``commands``.
"""

__version__ = "0.1.0"
