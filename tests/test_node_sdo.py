"""The node twin's own SDO server (CiA 301 §7.2.4), against canopen's SDO client and raw frames.

canopen's ``SdoClient`` (over a ``canopen.Network`` on a python-can virtual bus) is the master;
the cases a canopen client never produces (expedited download without size indication, a
toggle error, an abandoned transfer, an unknown command) are raw frames on a second bus of
the same channel, and every answer is checked byte for byte, multiplexer included. No
wall-clock limits: waits are "eventually" bounds, the server timeout is shortened per test.
"""

from __future__ import annotations

import queue
import struct
import time
import uuid

import can
import canopen
import pytest

from node_sim import sdo as sdo_mod
from node_sim.od import EDS_PATH
from node_sim.rig import Rig
from taxel_net.scene import BusSpec, Scene, TaxelSpec

WAIT = 5.0
NODE = 1
RX, TX = 0x600 + NODE, 0x580 + NODE
MARKER = 0x1ABCDEF  # extended ID: ignored by the node


def make_scene(channel: str, n: int = 2) -> Scene:
    taxels = tuple(TaxelSpec(node_id=i + 1, kind="R", zeta_mv=1.5, noise_mv=0.5, noise_sigma_mv=0.0,
                             x=10.0 * i, y=0.0, slope=0.1661, intercept=-0.0155) for i in range(n))
    return Scene(path="<test>", name="test", taxels=taxels,
                 bus=BusSpec(channels=(channel,), heartbeat_producer_ms=0))


class Raw:
    """A raw client on the channel: send one SDO request, get the node's next SDO answer."""

    def __init__(self, channel: str, network: canopen.Network):
        self.bus = can.Bus(interface="virtual", channel=channel, receive_own_messages=True)
        self.answers: queue.Queue[bytes] = queue.Queue()
        # canopen's client sees every answer too (and would take one for its own): after each
        # answer, wait until canopen's network has dispatched it as well (its SdoClient
        # discards stale answers when it starts a request)
        self.seen = 0
        self.network_seen = 0
        network.subscribe(TX, self._on_network)
        self.notifier = can.Notifier(self.bus, [self._on], timeout=0.05)

    def _on(self, msg: can.Message) -> None:
        if msg.arbitration_id == TX and not msg.is_extended_id:
            self.seen += 1
            self.answers.put(bytes(msg.data))
        elif msg.arbitration_id == MARKER and msg.is_extended_id:
            self.answers.put(b"marker")

    def request(self, data: bytes) -> bytes:
        self.send(data)
        return self.answer()

    def send(self, data: bytes) -> None:
        # drop the answers sent before this request (to canopen's client): the virtual bus
        # is FIFO, so they are all queued before our own marker frame comes back
        self.bus.send(can.Message(arbitration_id=MARKER, data=b"", is_extended_id=True))
        while self.answers.get(timeout=WAIT) != b"marker":
            pass
        self.bus.send(can.Message(arbitration_id=RX, data=data, is_extended_id=False))

    def _on_network(self, can_id, data, timestamp) -> None:
        self.network_seen += 1

    def answer(self, timeout: float = WAIT) -> bytes:
        answer = self.answers.get(timeout=timeout)
        deadline = time.monotonic() + WAIT
        while self.network_seen < self.seen and time.monotonic() < deadline:
            time.sleep(0.001)
        return answer

    def silent(self) -> bool:
        """No answer pending, after a round trip that is answered (FIFO virtual bus)."""
        ping = self.request(struct.pack("<BHB", 0x40, 0x1000, 0) + bytes(4))
        return ping[0] == 0x43 and ping[1:4] == struct.pack("<HB", 0x1000, 0)

    def close(self) -> None:
        self.notifier.stop()
        self.bus.shutdown()


class Setup:
    def __init__(self, channel: str):
        self.rig = Rig(make_scene(channel)).start()
        self.node = self.rig.node(NODE)
        self.network = canopen.Network()
        self.network.connect(interface="virtual", channel=channel)
        self.remote = canopen.RemoteNode(NODE, str(EDS_PATH))
        self.remote.sdo.RESPONSE_TIMEOUT = 2.0
        self.network.add_node(self.remote)
        self.raw = Raw(channel, self.network)

    def close(self) -> None:
        self.raw.close()
        self.network.disconnect()
        self.rig.stop()


@pytest.fixture
def s():
    setup = Setup(f"test-sdo-{uuid.uuid4().hex[:10]}")
    yield setup
    setup.close()


def abort_frame(index: int, subindex: int, code: int) -> bytes:
    return struct.pack("<BHBL", 0x80, index, subindex, code)


def initiate(command: int, index: int, subindex: int, payload: bytes = bytes(4)) -> bytes:
    return struct.pack("<BHB", command, index, subindex) + payload.ljust(4, b"\0")


def _abort(fn) -> int:
    with pytest.raises(canopen.SdoAbortedError) as info:
        fn()
    return info.value.code


# ------------------------------------------------------------------------ expedited

def test_expedited_download_without_size_indication(s):
    """Command 0x22 (e = 1, s = 0): the object's own size is taken from the 4 data bytes."""
    raw = s.raw
    assert raw.request(initiate(0x22, 0x1017, 0, struct.pack("<H", 45) + b"\xAA\xBB")) == \
        struct.pack("<BHBL", 0x60, 0x1017, 0, 0)
    assert s.remote.sdo[0x1017].raw == 45
    assert raw.request(initiate(0x22, 0x1800, 2, b"\x03\xFF\xFF\xFF")) == struct.pack("<BHBL", 0x60, 0x1800, 2, 0)
    assert s.remote.sdo[0x1800][2].raw == 3
    assert raw.request(initiate(0x22, 0x2001, 1, struct.pack("<f", 2.5))) == struct.pack("<BHBL", 0x60, 0x2001, 1, 0)
    assert s.remote.sdo[0x2001][1].raw == 2.5
    # the value checks still apply
    assert raw.request(initiate(0x22, 0x2001, 1, struct.pack("<f", -1.0))) == abort_frame(0x2001, 1, 0x06090032)


def test_expedited_download_with_size_indication(s):
    # 0x2F: e = 1, s = 1, n = 3 -> 1 byte; 0x2B: 2 bytes; a wrong indicated size is a length error
    assert s.raw.request(initiate(0x2F, 0x1800, 2, b"\x05")) == struct.pack("<BHBL", 0x60, 0x1800, 2, 0)
    assert s.remote.sdo[0x1800][2].raw == 5
    assert s.raw.request(initiate(0x2B, 0x1017, 0, struct.pack("<H", 12))) == struct.pack("<BHBL", 0x60, 0x1017, 0, 0)
    assert s.remote.sdo[0x1017].raw == 12
    assert s.raw.request(initiate(0x2F, 0x1017, 0, b"\x01")) == abort_frame(0x1017, 0, 0x06070010)
    # and through canopen's client (which always indicates the size)
    s.remote.sdo[0x1017].raw = 0
    assert s.remote.sdo[0x1017].raw == 0


# ------------------------------------------------------------------------ abort multiplexer

def test_aborts_carry_the_multiplexer_of_the_request(s):
    raw = s.raw
    assert raw.request(initiate(0x40, 0x1000, 0))[0] == 0x43          # a transfer of 0x1000:0 first
    assert raw.request(initiate(0x40, 0x2FFF, 0)) == abort_frame(0x2FFF, 0, 0x06020000)
    assert raw.request(initiate(0x40, 0x1000, 0))[0] == 0x43
    assert raw.request(initiate(0x2F, 0x2000, 0, b"\x01")) == abort_frame(0x2000, 0, 0x06010002)
    assert raw.request(initiate(0x40, 0x2001, 9)) == abort_frame(0x2001, 9, 0x06090011)
    assert raw.request(initiate(0x40, 0x1017, 1)) == abort_frame(0x1017, 1, 0x06090011)   # sub > 0 of a VAR
    assert raw.request(initiate(0x23, 0x2001, 1, struct.pack("<f", float("nan")))) == \
        abort_frame(0x2001, 1, 0x06090030)
    # canopen's master sees the codes
    assert _abort(lambda: s.remote.sdo.upload(0x2FFF, 0)) == 0x06020000
    assert _abort(lambda: s.remote.sdo.download(0x2000, 0, b"\x01")) == 0x06010002


# ------------------------------------------------------------------------ segmented

def test_segmented_download_checked_at_initiate(s):
    raw = s.raw
    # read-only, const, missing object / sub-index: refused in answer to the initiate
    assert raw.request(initiate(0x21, 0x2000, 0, struct.pack("<L", 1))) == abort_frame(0x2000, 0, 0x06010002)
    assert raw.request(initiate(0x21, 0x1008, 0, struct.pack("<L", 3))) == abort_frame(0x1008, 0, 0x06010002)
    assert raw.request(initiate(0x21, 0x2FFF, 0, struct.pack("<L", 4))) == abort_frame(0x2FFF, 0, 0x06020000)
    assert raw.request(initiate(0x21, 0x2001, 7, struct.pack("<L", 4))) == abort_frame(0x2001, 7, 0x06090011)
    # an indicated size that cannot be the object's (REAL32 needs 4)
    assert raw.request(initiate(0x21, 0x2001, 1, struct.pack("<L", 2))) == abort_frame(0x2001, 1, 0x06070010)
    # no transfer was started: a segment now is a command out of place
    assert raw.request(bytes([0x00]) + bytes(7)) == abort_frame(0, 0, 0x05040001)
    # canopen's client, forced to segment: the same codes
    assert _abort(lambda: s.remote.sdo.download(0x2000, 0, b"\x01", force_segment=True)) == 0x06010002
    assert _abort(lambda: s.remote.sdo.download(0x2FFF, 0, b"\x01", force_segment=True)) == 0x06020000


def test_segmented_transfers_with_canopen_client(s):
    rn = s.remote
    rn.sdo.download(0x2001, 1, struct.pack("<f", 3.75), force_segment=True)
    assert rn.sdo[0x2001][1].raw == 3.75
    assert _abort(lambda: rn.sdo.download(0x2001, 1, struct.pack("<f", -1.0), force_segment=True)) == 0x06090032
    assert rn.sdo[0x1008].raw == "taxel node twin"        # segmented upload, 15 bytes
    # segmented download without size indication, then a raw one with the size
    raw = s.raw
    assert raw.request(initiate(0x20, 0x2001, 2)) == struct.pack("<BHBL", 0x60, 0x2001, 2, 0)
    assert raw.request(bytes([0x07]) + struct.pack("<f", 0.25) + bytes(3)) == bytes([0x20]) + bytes(7)
    assert rn.sdo[0x2001][2].raw == 0.25
    # more data than indicated: length error with the transfer's multiplexer
    assert raw.request(initiate(0x21, 0x2001, 2, struct.pack("<L", 4))) == struct.pack("<BHBL", 0x60, 0x2001, 2, 0)
    assert raw.request(bytes([0x01]) + bytes(7)) == abort_frame(0x2001, 2, 0x06070010)


def test_toggle_error_and_client_abort(s):
    raw = s.raw
    assert raw.request(initiate(0x21, 0x2001, 1, struct.pack("<L", 4))) == struct.pack("<BHBL", 0x60, 0x2001, 1, 0)
    assert raw.request(bytes([0x10]) + bytes(7)) == abort_frame(0x2001, 1, 0x05030000)   # toggle 1 first
    # segmented upload: second segment request with the toggle not alternated
    assert raw.request(initiate(0x40, 0x1008, 0)) == struct.pack("<BHBL", 0x41, 0x1008, 0, 15)
    assert raw.request(bytes([0x60]) + bytes(7)) == bytes([0x00]) + b"taxel n"
    assert raw.request(bytes([0x60]) + bytes(7)) == abort_frame(0x1008, 0, 0x05030000)
    # an abort from the client ends the transfer without an answer
    assert raw.request(initiate(0x40, 0x1008, 0))[0] == 0x41
    raw.send(abort_frame(0x1008, 0, 0x08000000))
    assert raw.request(bytes([0x60]) + bytes(7)) == abort_frame(0, 0, 0x05040001)
    assert raw.silent()


def test_unknown_and_block_commands_refused(s):
    raw = s.raw
    assert raw.request(initiate(0xE0, 0x2001, 1)) == abort_frame(0x2001, 1, 0x05040001)      # ccs 7
    assert raw.request(initiate(0xC2, 0x2001, 1, struct.pack("<L", 4))) == abort_frame(0x2001, 1, 0x05040001)
    # block upload: threshold 0 -> refused; threshold >= size -> CiA 301 protocol switch
    assert raw.request(struct.pack("<BHBBB", 0xA4, 0x2001, 1, 127, 0) + bytes(2)) == abort_frame(0x2001, 1, 0x05040001)
    assert raw.request(struct.pack("<BHBBB", 0xA4, 0x2001, 1, 127, 4) + bytes(2)) == \
        bytes([0x43, 0x01, 0x20, 0x01]) + struct.pack("<f", 1.5)
    rn = s.remote
    assert _abort(lambda: rn.sdo[0x2001][1].open("rb", block_transfer=True).read()) == 0x05040001
    assert _abort(lambda: rn.sdo[0x2001][1].open("wb", block_transfer=True).write(b"\0" * 4)) == 0x05040001


# ------------------------------------------------------------------------ server timeout

def test_server_timeout_aborts_an_abandoned_transfer(s):
    assert s.node.sdo.timeout_s == sdo_mod.DEFAULT_TIMEOUT_S == 1.0   # CANopenNode's default
    s.node.sdo.timeout_s = 0.05
    raw = s.raw
    # download abandoned after the initiate
    assert raw.request(initiate(0x21, 0x2001, 1, struct.pack("<L", 4))) == struct.pack("<BHBL", 0x60, 0x2001, 1, 0)
    assert raw.answer() == abort_frame(0x2001, 1, 0x05040000)
    assert not s.node.sdo.busy
    # upload abandoned after a segment: the timer restarts on every segment
    assert raw.request(initiate(0x40, 0x1008, 0))[0] == 0x41
    assert raw.request(bytes([0x60]) + bytes(7))[0] == 0x00
    assert raw.answer() == abort_frame(0x1008, 0, 0x05040000)
    # a completed transfer leaves no timer behind
    assert s.remote.sdo[0x1008].raw == "taxel node twin"
    assert not s.node.sdo.busy
    assert raw.silent()
    with pytest.raises(queue.Empty):
        raw.answer(timeout=0.3)   # nothing more is sent (6 timeouts)


def test_stopped_node_drops_the_transfer(s):
    raw = s.raw
    assert raw.request(initiate(0x21, 0x2001, 1, struct.pack("<L", 4)))[0] == 0x60
    assert s.node.sdo.busy
    s.network.send_message(0x000, bytes([0x02, NODE]))       # NMT stop
    s.network.send_message(0x000, bytes([0x80, NODE]))       # back to pre-operational
    assert raw.request(bytes([0x07]) + bytes(7)) == abort_frame(0, 0, 0x05040001)
