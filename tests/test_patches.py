"""The shared PDO layout of patch nodes (taxel_net.patches): hand-worked frames and scene checks."""

import dataclasses
import math

import numpy as np
import pytest

from taxel_net.errors import SceneError
from taxel_net.patches import (ENC_BITS, ENC_INT8, ENC_INT16, PatchFrameError, Tpdo, devices, fd_length, pack,
                               readings_to_counts, unpack)
from taxel_net.scene import BusSpec, FusionSpec, Scene, TaxelSpec, load_scene


def patch_scene(sizes, mode="decision", sync_counter=64, fd=False, raw_format="int16", channels=("c0",)):
    taxels = []
    for node, size in enumerate(sizes, start=1):
        taxels += [TaxelSpec(node_id=node, kind="C") for _ in range(size)]
    bus = BusSpec(mode=mode, sync_counter=sync_counter, fd=fd, patch_nodes=True, raw_format=raw_format,
                  channels=channels)
    return Scene(path="<t>", name="t", bus=bus, taxels=tuple(taxels), fusion=FusionSpec())


def test_decisions_pack_one_bit_per_taxel_lsb_first_behind_the_tag():
    # 10 taxels, tagged: byte 0 = tag, byte 1 = taxels 0-7 (taxel 0 in bit 0), byte 2 = taxels 8-9
    (dev,) = devices(patch_scene([10]))
    (t,) = dev.tpdos
    assert (t.cob_id, t.count, t.length, t.tagged) == (0x181, 10, 3, True)
    u = np.array([1, -1, -1, 1, -1, -1, -1, -1, 1, 1])
    assert pack(t, u, tag=37) == bytes([37, 0b0000_1001, 0b11])
    tag, back = unpack(t, bytes([37, 0b0000_1001, 0b11]))
    assert tag == 37 and back.tolist() == u.tolist()


def test_a_192_taxel_patch_needs_four_classic_frames_or_one_fd_frame():
    # 7 decision bytes (56 taxels) per tagged classic frame: 56 + 56 + 56 + 24
    (dev,) = devices(patch_scene([192]))
    assert [(t.cob_id, t.first, t.count, t.length) for t in dev.tpdos] == [
        (0x181, 0, 56, 8), (0x182, 56, 56, 8), (0x183, 112, 56, 8), (0x184, 168, 24, 4)]
    (fd,) = devices(patch_scene([192], fd=True))
    assert [(t.count, t.length, t.fd) for t in fd.tpdos] == [(192, 32, True)]  # 1 + 24 bytes -> FD length 32


def test_cob_ids_run_on_per_channel_across_devices_and_untagged_frames_carry_eight_bytes():
    a, b = devices(patch_scene([64, 65], sync_counter=0))
    assert [(t.cob_id, t.count, t.length) for t in a.tpdos] == [(0x181, 64, 8)]
    assert [(t.cob_id, t.count, t.length) for t in b.tpdos] == [(0x182, 64, 8), (0x183, 1, 1)]


def test_fd_lengths_round_up_to_the_valid_data_lengths():
    assert [fd_length(n) for n in (0, 8, 9, 13, 17, 21, 25, 33, 49, 64)] == [0, 8, 12, 16, 20, 24, 32, 48, 64, 64]
    with pytest.raises(ValueError):
        fd_length(65)


def test_raw_readings_round_saturate_and_mark_not_valid():
    (dev,) = devices(patch_scene([3], mode="raw", raw_format="int8"))
    (t,) = dev.tpdos
    assert t.encoding == ENC_INT8 and t.length == 4
    counts, saturated = readings_to_counts(t, [1.26, -20.0, math.nan], 0.1)
    assert counts.tolist() == [13, -127, -128] and saturated == 1
    data = pack(t, counts, tag=5)
    assert data == bytes([5, 13, 0x81, 0x80])
    tag, mv = unpack(t, data, 0.1)
    assert tag == 5 and mv[0] == pytest.approx(1.3) and mv[1] == pytest.approx(-12.7) and math.isnan(mv[2])


def test_int16_little_endian():
    t = Tpdo(0, 0x181, 0, 2, ENC_INT16, False, 4, False)
    assert pack(t, np.array([0x1234, -2])) == bytes([0x34, 0x12, 0xFE, 0xFF])


def test_wrong_length_and_set_padding_bits_are_refused_with_the_centres_counter():
    t = Tpdo(0, 0x181, 0, 10, ENC_BITS, True, 3, False)
    with pytest.raises(PatchFrameError) as e:
        unpack(t, bytes(4))
    assert e.value.reason == "bad_dlc"
    with pytest.raises(PatchFrameError) as e:
        unpack(t, bytes([0, 0, 0b100]))      # bit of a taxel 10 that does not exist
    assert e.value.reason == "bad_value"
    fd = Tpdo(0, 0x181, 0, 10, ENC_BITS, True, 12, True)
    with pytest.raises(PatchFrameError):
        unpack(fd, bytes(11) + b"\x01")     # FD padding byte


def test_bundled_skin_scenes_load_with_their_layouts():
    sc = load_scene("scenes/skin4096.toml")
    devs = devices(sc)
    assert sc.n == 4096 and len(sc.bus.channels) == 8 and len(devs) == 24
    assert sorted({len(d.taxels) for d in devs}) == [128, 192]
    assert sorted(i for d in devs for i in d.taxels) == list(range(4096))  # every taxel in exactly one device
    per = load_scene("scenes/skin4096_per_taxel.toml")
    assert len(per.bus.channels) == 33 and len(devices(per)) == 4096


def _scene_text(bus_extra: str, rows: str) -> str:
    return f"""
[scene]
name = "t"
[bus]
channels = ["a"]
{bus_extra}
[fusion]
tuple = "pm1"
{rows}
"""


@pytest.mark.parametrize("bus_extra, rows, field", [
    ("", "[[taxels]]\nnode_id = 1\nkind = 'C'\n[[taxels]]\nnode_id = 1\nkind = 'C'\n", "taxels[1].node_id"),
    ("patch_nodes = true\nraw_format = 'real32'", "[[taxels]]\nnode_id = 1\nkind = 'C'\n", "bus.raw_format"),
    ("raw_format = 'int8'", "[[taxels]]\nnode_id = 1\nkind = 'C'\n", "bus.raw_format"),
    ("data_bitrate = 5000000", "[[taxels]]\nnode_id = 1\nkind = 'C'\n", "bus.data_bitrate"),
    ("fd = true\ndata_bitrate = 500000", "[[taxels]]\nnode_id = 1\nkind = 'C'\n", "bus.data_bitrate"),
    ("patch_nodes = 1", "[[taxels]]\nnode_id = 1\nkind = 'C'\n", "bus.patch_nodes"),
    ("tpdo_cob_id_base = 0x200", "[[taxels]]\nnode_id = 1\nkind = 'C'\n", "bus.tpdo_cob_id_base"),
    ("patch_nodes = true\ntpdo_cob_id_base = 0x57F",
     "[[taxels]]\nnode_id = 1\nkind = 'C'\n[[taxels]]\nnode_id = 2\nkind = 'C'\n", "bus.tpdo_cob_id_base"),
])
def test_scene_errors_name_the_field(tmp_path, bus_extra, rows, field):
    p = tmp_path / "s.toml"
    p.write_text(_scene_text(bus_extra, rows))
    with pytest.raises(SceneError) as e:
        load_scene(p)
    assert field in str(e.value)


def test_a_patch_node_holds_at_most_254_taxels(tmp_path):
    p = tmp_path / "s.toml"
    rows = "".join("[[taxels]]\nnode_id = 1\nkind = 'C'\n" for _ in range(255))
    p.write_text(_scene_text("patch_nodes = true", rows))
    with pytest.raises(SceneError, match="taxels\\[254\\].node_id.*at most 254"):
        load_scene(p)
    sc = dataclasses.replace(patch_scene([254]))
    assert len(devices(sc)[0].taxels) == 254
