"""The fusion centre's service around patch nodes (issue 14): thresholds of the centralised
tests at scale, the master's configuration of patch nodes against a stand-in SDO server."""

import numpy as np
import pytest

from fusion_center.service.centralised_tests import glrt_threshold


@pytest.mark.parametrize("n, d, alpha", [(40, 2.0, 0.01), (200, 5.0, 0.002)])
def test_the_exact_glrt_law_gives_the_monte_carlo_quantile(n, d, alpha):
    # sum_i max(0, LLR_i), LLR_i ~ N(-d_i^2/2, d_i^2): P0(U > tau) = alpha within the sampling error
    dd = np.full(n, d)
    dd[: n // 4] = 1.5 * d
    tau = glrt_threshold(dd, alpha)
    rng = np.random.default_rng(3)
    m = 200_000
    u = np.maximum(rng.standard_normal((m, n)) * dd - dd * dd / 2, 0).sum(axis=1)
    p = float(np.mean(u > tau))
    sd = np.sqrt(alpha * (1 - alpha) / m)
    assert p <= alpha + 3 * sd and p >= alpha - 6 * sd - alpha * 0.05  # conservative by at most a grid step


# ---------------------------------------------------------------------------- end to end
import contextlib  # noqa: E402
import dataclasses  # noqa: E402
import uuid  # noqa: E402
from pathlib import Path  # noqa: E402

from fusion_center.core.encoding import local_decision  # noqa: E402
from fusion_center.service.pipeline import taxel_labels  # noqa: E402
from node_sim import physics  # noqa: E402
from taxel_net.patches import devices  # noqa: E402
from taxel_net.scene import load_scene  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent


def small_skin(name="skin4096", channels=2):
    """The first ``channels`` buses of a bundled skin: 512 taxels (three patch nodes) each."""
    sc = load_scene(ROOT / "scenes" / f"{name}.toml")
    taxels = tuple(t for t in sc.taxels if t.channel < channels)
    return dataclasses.replace(sc, taxels=taxels, bus=dataclasses.replace(sc.bus, channels=sc.bus.channels[:channels]))


@contextlib.contextmanager
def booted_by_the_centre(scene):
    """The scene's twins and a centre on fresh virtual buses, booted (every node configured
    over SDO, none missing): yields (service, rig), stops both after."""
    from fusion_center.service import FusionService
    from node_sim.rig import Rig

    tag = uuid.uuid4().hex[:8]
    channels = [f"boot-{tag}-{c}" for c in scene.bus.channels]
    svc = FusionService(scene, interface="virtual", channels=channels, truth=False)
    rig = Rig(scene, interface="virtual", channel=channels)
    with svc:
        rig.start()
        try:
            assert svc.boot(5.0) == []
            yield svc, rig
        finally:
            rig.stop()


def check_records(scene, records):
    """Records against the physics of their cycle (as bench/junk_flood.py): a complete record's
    present taxels are exactly the twins' decisions of that cycle; a degraded one's a subset."""
    zeta = np.array([t.zeta_mv for t in scene.taxels])
    noise = np.array([t.noise_mv for t in scene.taxels])
    labels = taxel_labels(scene)
    complete = wrong = 0
    for r in records:
        if r["n_received"] == 0:
            continue
        x = physics.sample_readings(scene, r["cycle"])
        if scene.bus.mode == "raw":
            top = 127 if scene.bus.raw_format == "int8" else 32767
            x = np.clip(np.rint(x / scene.bus.raw_lsb_mv), -top, top) * scene.bus.raw_lsb_mv
        present = {labels[i] for i in np.flatnonzero(local_decision(x, noise, zeta, "pm1") == 1)}
        got = set(r["present_nodes"])
        if not r["degraded"]:
            complete += 1
            wrong += got != present
        else:
            wrong += not got <= present
    return complete, wrong


@pytest.mark.parametrize("name, trace", [("skin4096", "t.log"), ("skin4096_fd", "t.blf")])
def test_demo_of_patch_nodes_decides_every_cycle_from_its_own_decisions_and_replays(name, trace, tmp_path):
    from fusion_center.commands.demo import run_demo
    from fusion_center.service import replay_trace

    scene = small_skin(name)
    assert len(devices(scene)) == 6 and scene.n == 1024
    svc, summary = run_demo(scene, 30, trace=tmp_path / trace, keep_records=True,
                            channel_tag=uuid.uuid4().hex[:8])
    records = list(svc.records)
    assert len(records) == 30 and summary["sdo"]["aborts"] == 0 and summary["sdo"]["timeouts"] == 0
    complete, wrong = check_records(scene, records)
    assert wrong == 0 and complete >= 5, (complete, wrong)
    counters = summary["counters"]
    assert counters["tpdo1"] > 0 and counters.get("fd_frame", 0) == 0 and counters.get("bad_dlc", 0) == 0
    # the trace keeps the FD frames (is_fd, BRS): replay decides the same
    replayed, _ = replay_trace(scene, tmp_path / trace, truth=True)
    assert replayed == records
    # and `fusion-center replay` takes it as the scene's (patch TPDO COB-IDs are allotted per
    # channel, not node-ID based), but not as a recording of the other mode
    from fusion_center.service.traces import check_trace
    from taxel_net.errors import UsageError

    counts = check_trace(scene, tmp_path / trace)
    assert counts["foreign"] == 0 and counts["tpdo1"] > 0 and counts["tpdo2"] == 0, counts
    raw = dataclasses.replace(scene, bus=dataclasses.replace(scene.bus, mode="raw"))
    with pytest.raises(UsageError, match="recorded in decision mode"):
        check_trace(raw, tmp_path / trace)


def test_the_master_configures_the_patch_twins_as_their_tpdos_describe():
    from fusion_center.service.node_config import patch_configuration

    scene = small_skin("skin4096_raw", channels=1)
    touched = scene.taxels[int(np.argmax(physics.signal_batch(scene, np.arange(scene.cycles)).sum(axis=0)))]
    scene = dataclasses.replace(scene, taxels=tuple(t for t in scene.taxels if t.node_id == touched.node_id))
    with booted_by_the_centre(scene) as (svc, rig):
        m = svc.master
        writes = [w for d in devices(scene) for w in patch_configuration(scene, d)]
        assert m.sdo_writes == len(writes) and m.sdo_aborts == 0 and m.sdo_timeouts == 0
        for d in devices(scene):
            od = rig.node(d.node_id, d.channel).local.sdo
            for t in d.tpdos:  # what the twin holds: the last value written
                assert od[0x1800 + t.number][1].raw == 0x4000_0000 | t.cob_id
                assert od[0x1800 + t.number][2].raw == scene.bus.transmission_type
                n = od[0x1A00 + t.number][0].raw
                entries = [od[0x1A00 + t.number][k].raw for k in range(1, n + 1)]
                assert entries[0] == 0x2021_0008 and len(entries) == 1 + t.count
                assert entries[1] == 0x2030_0008 | (t.first + 1) << 8  # INTEGER8 readings
            assert od[0x1019].raw == scene.bus.sync_counter and od[0x1017].raw == scene.bus.heartbeat_producer_ms
            assert od[0x2032].raw == pytest.approx(scene.bus.raw_lsb_mv)
            for k, i in enumerate(d.taxels[:5]):  # the detector arrays, per taxel
                assert od[0x2010][k + 1].raw == pytest.approx(scene.taxels[i].zeta_mv)
                assert od[0x2011][k + 1].raw == pytest.approx(scene.taxels[i].noise_mv)
