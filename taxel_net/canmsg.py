"""CAN glue shared by the fusion centre's service and the node twins (not numerical core).

:class:`TxMessage` is a frame this process sends: a plain ``can.Message`` whose deep copy is
cheap. python-can's ``virtual`` interface deep-copies every sent frame once per receiving bus,
and ``Message.__deepcopy__`` goes through ``copy.deepcopy`` of the channel and the data
bytearray (~5 µs a frame: most of a node twin's cost per frame, and on the master's SYNC path).
This copy builds the same ``can.Message`` directly (the data copied into a new bytearray; the
channel is a str, int or None, immutable); every other field is copied as python-can does.
Other interfaces never copy.
"""

from __future__ import annotations

import can


class TxMessage(can.Message):
    """A ``can.Message`` with a cheap, field-for-field ``__deepcopy__`` (see module docstring)."""

    __slots__ = ()

    def __deepcopy__(self, memo) -> can.Message:
        return can.Message(
            timestamp=self.timestamp, arbitration_id=self.arbitration_id,
            is_extended_id=self.is_extended_id, is_remote_frame=self.is_remote_frame,
            is_error_frame=self.is_error_frame, channel=self.channel, dlc=self.dlc,
            data=bytearray(self.data), is_fd=self.is_fd, is_rx=self.is_rx,
            bitrate_switch=self.bitrate_switch, error_state_indicator=self.error_state_indicator)
