"""COB-ID tables (CiA 301 predefined connection set) and payload decoding."""

import math
import struct

import pytest

from taxel_net.scene import BusSpec, Scene, TaxelSpec
from fusion_center.service import decoder as d


def two_channel_scene():
    taxels = (TaxelSpec(node_id=5, kind="R"), TaxelSpec(node_id=127, kind="C"),
              TaxelSpec(node_id=5, kind="P", channel=1))
    return Scene(path="<t>", name="t", bus=BusSpec(channels=("a", "b")), taxels=taxels)


def test_predefined_connection_set_cob_ids():
    tables = d.build_cob_tables(two_channel_scene())
    t0, t1 = tables
    # CiA 301 table 72: EMCY 0x81-0xFF, TPDO1 0x181-0x1FF, TPDO2 0x281-0x2FF,
    # SDO tx 0x581-0x5FF, SDO rx 0x601-0x67F, NMT error control 0x701-0x77F
    assert t0[0x185] == (d.K_TPDO1, 0) and t0[0x1FF] == (d.K_TPDO1, 1)
    assert t0[0x285] == (d.K_TPDO2, 0) and t0[0x77F] == (d.K_HEARTBEAT, 1)
    assert t0[0x85] == (d.K_EMCY, 0) and t0[0x585] == (d.K_SDO_RESPONSE, 0) and t0[0x605] == (d.K_SDO_REQUEST, 0)
    assert t0[0x000][0] == d.K_NMT and t0[0x080][0] == d.K_SYNC and t0[0x100][0] == d.K_TIME
    assert t1[0x185] == (d.K_TPDO1, 2)  # same node-ID on the second network
    assert 0x1FF not in t1 and 0x186 not in t0


@pytest.mark.parametrize("byte,value", [(0x01, 1), (0xFF, -1), (0x7F, 127), (0x80, -128), (0x00, 0)])
def test_integer8_two_complement(byte, value):
    assert d.decode_decision(bytes([byte])) == value == struct.unpack("b", bytes([byte]))[0]


def test_real32_little_endian():
    # 3.5 = 0x40600000 as IEEE 754 binary32, little endian on CANopen
    assert d.decode_real32(bytes([0x00, 0x00, 0x60, 0x40])) == 3.5
    assert math.isnan(d.decode_real32(bytes([0x00, 0x00, 0xC0, 0x7F])))
    assert d.decode_real32(d.encode_real32(-0.0155)) == pytest.approx(-0.0155, rel=1e-7)


def test_emcy_layout():
    # CiA 301 7.2.7.3.1: bytes 0-1 error code (LE), byte 2 error register, 3-7 manufacturer
    code, register, manufacturer = d.decode_emcy(bytes([0x00, 0x81, 0x11, 9, 8, 7, 6, 5]))
    assert (code, register, manufacturer) == (0x8100, 0x11, bytes([9, 8, 7, 6, 5]))


def test_sync_payload():
    assert d.sync_payload(None) == b"" and d.sync_payload(240) == b"\xf0"
