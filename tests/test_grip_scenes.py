"""The bundled grasp scenes of issue 23 through the centre's control code offline (bench/grasp_sim.py:
the grasp world, the drive twin per SYNC, the taxels' view and the nodes' detector, CyclePipeline,
the grip law, the drive's RPDO): what each scene is for happens, checked against the world's truth
and against numbers worked by hand from the scenes' values."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "bench"))

from grasp import Case, grasp_metrics  # noqa: E402
from grasp_sim import run_grasp  # noqa: E402

from taxel_net.scene import load_scene  # noqa: E402

G = 9.80665

# row fields of grasp_sim.run_grasp
K, PHASE, NORMAL, MIN_HOLD, SLIPPING, SLID, DROPPED, CRUSHED, COMMAND, CENTRE_SLIP, IN_GRIP, FLAGS, MODE = range(13)


def run(name, mode=None, fixed_n=None):
    scene = load_scene(name)
    rows = run_grasp(scene, mode or scene.bus.mode, fixed_n=fixed_n)["rows"]
    return scene, rows


@pytest.mark.parametrize("name", ["grasp_lift", "grasp_lift_raw"])
def test_lift_slips_under_the_first_squeeze_and_is_caught(name):
    """0.5 kg, mu_s 0.5: least holding force m g / (2 mu_s) = 4.903 N at rest, m (g + 4) / (2 mu_s)
    = 6.903 N in the lift; the law squeezes 6 N: the object slips in the lift, never at rest; the
    centre flags it, raises, and the object is carried to the end, not lost."""
    scene, rows = run(name)
    assert scene.grip.grasp_n == 6.0
    assert 0.5 * G / (2 * 0.5) == pytest.approx(4.903, abs=1e-3)
    assert 0.5 * G / (2 * 0.5) < 6.0 < 0.5 * (G + 4.0) / (2 * 0.5)
    slips = [r for r in rows if r[SLIPPING] and r[PHASE] in ("close", "lift", "hold")]
    assert slips and slips[0][PHASE] == "lift"
    onset = slips[0][K]
    assert slips[0][MIN_HOLD] == pytest.approx(6.903, abs=2e-3)           # the lift's least holding force
    detected = next(r[K] for r in rows if r[CENTRE_SLIP])
    # the 2 mm pads have a pressure cell on each edge of the 20 mm footprint at rest: the first
    # millimetre of slide switches the top one off (the edge cue, 0.625 mm > 0.4 x the 1 mm band);
    # the SYNC after the onset's step samples it, the next confirms it: 2 cycles (a full pitch, the
    # band alone, took 4)
    assert detected - onset == 2
    raises = [r for r in rows if "slip_raise" in r[FLAGS]]
    assert raises[0][COMMAND] == pytest.approx(18.0)              # 3 x the 6 N it slipped under
    # 18 N stops it (> m (g + a) / (2 mu_k) = 8.63 N); the centre's flags trailing the slide raise no
    # more once the 18 N arrived (the law before raised to the drive's 40 N, 60 ms after the send)
    assert len(raises) == 1
    assert not rows[-1][DROPPED] and rows[-1][MODE] != "left"
    hold = [r for r in rows if r[PHASE] == "hold"]
    assert not any(r[SLIPPING] for r in hold)
    # well within the 30 mm (grip_at 20 + contact 20 / 2) at which the contact leaves the pads
    assert max(r[SLID] for r in rows if r[PHASE] in ("lift", "hold")) < 15.0
    # the floor the slip taught: 1.2 x 6 N; the hold ends there (raw: the floor gives way to 1.2 x eq 26a)
    end = hold[-1][COMMAND]
    if name == "grasp_lift":
        assert end == pytest.approx(7.2)
    else:
        assert 1.2 * 4.903 - 0.05 <= end < 7.2


@pytest.mark.parametrize("name", ["grasp_lift", "grasp_lift_raw"])
@pytest.mark.parametrize("grip_at", [20.95, 19.3])
def test_a_contact_off_the_pads_middle_is_no_slip_as_the_jaws_press(name, grip_at):
    """The contact 0.95 mm above / 0.7 mm below the pads' middle (bench/grasp.py's contacts lie
    anywhere within a pitch of it): at 20.95 mm the 20 mm footprint covers the 2 mm row's cells at
    12 .. 30 mm, whose mean (21 mm) is not the presence and thin-beam cells' (20 mm), so the
    centroid of the 16 present locations moves by (10 x 21 + 6 x 20) / 16 - 20 = 0.625 mm as the
    jaws press - 0.625 of the band, beyond the edge cue's 0.4, and no slip. The centre flags nothing
    before the world's first slip (the lift's), and its first raise is that slip's: 3 x 6 N."""
    import dataclasses

    base = load_scene(name)
    scene = dataclasses.replace(base, grasp=dataclasses.replace(base.grasp, grip_at_mm=grip_at))
    rows = run_grasp(scene, scene.bus.mode)["rows"]
    assert (10 * 21 + 6 * 20) / 16 - 20 == pytest.approx(0.625)
    slips = [r for r in rows if r[SLIPPING] and r[PHASE] in ("close", "lift", "hold")]
    assert slips and slips[0][PHASE] == "lift"
    onset = slips[0][K]
    first_flag = next(r[K] for r in rows if r[CENTRE_SLIP])
    assert first_flag > onset
    assert not any("slip_raise" in r[FLAGS] for r in rows if r[K] < onset)
    raises = [r for r in rows if "slip_raise" in r[FLAGS]]
    assert raises and raises[0][COMMAND] == pytest.approx(18.0)
    assert not rows[-1][DROPPED] and rows[-1][MODE] != "left"


def test_fragile_is_held_below_its_crushing_force_which_the_vendors_grip_exceeds():
    """0.2 kg, mu_s 0.6, crushed above 3 N: the vendors' 2 x 1.634 N = 3.27 N crushes it. The law
    squeezes 2.4 N (the 2 m/s² lift needs 0.2 (g + 2) / 1.2 = 1.968 N) and does not probe: 1.7 x
    2.4 N is above max_n = 2.7 N (a slip it began could need more than it may squeeze). Held to
    the place, never slipping, never crushed."""
    scene, rows = run("grasp_fragile")
    least = 0.2 * G / (2 * 0.6)
    assert least == pytest.approx(1.634, abs=1e-3)
    assert 0.2 * (G + 2.0) / (2 * 0.6) < 2.4 and 1.7 * 2.4 > scene.grip.max_n == 2.7
    held = [r for r in rows if r[PHASE] in ("lift", "hold")]
    assert all(r[COMMAND] == pytest.approx(2.4) for r in held)
    assert not any(r[SLIPPING] for r in held)
    assert max(r[NORMAL] for r in rows) <= 2.4 + 1e-9
    assert not rows[-1][CRUSHED] and not rows[-1][DROPPED]
    _, vendor = run("grasp_fragile", "fixed", fixed_n=2 * least)
    assert vendor[-1][CRUSHED]


def test_offline_grasp_is_deterministic():
    a = run("grasp_fragile")[1]
    b = run("grasp_fragile")[1]
    assert a == b


def test_grasp_metrics_on_hand_made_rows():
    """Episodes, detection, stuck time, slide and the holding ratio from rows written by hand."""
    def row(k, phase, slipping=False, slid=0.0, det=False, normal=6.0, least=5.0):
        return (k, phase, normal, least, slipping, slid, False, False, normal, det, True, (), "stick")
    rows = [row(0, "close"), row(1, "lift"), row(2, "lift", True, 0.5), row(3, "lift", True, 2.5),
            row(4, "lift", True, 4.0, det=True), row(5, "lift", False, 4.0), row(6, "hold", slid=4.0),
            row(7, "hold", slid=4.0, normal=6.0, least=5.0)]
    case = Case(index=0, mass_kg=0.5, mu_s=0.5, mu_k=0.4, accel_m_s2=2.0, disturbance="none", disturb_at_s=0.0,
                load_kg=0.0, shake_m_s2=0.0, shake_hz=0.0, pitch_mm=2.0, fragile=False, max_force_n=None, grasp_n=6.0)
    m = grasp_metrics(rows, case, 0.01)
    (ep,) = m["episodes"]
    assert (ep["onset"], ep["end"], ep["stuck_ms"], ep["detect_cycles"]) == (2, 5, 30.0, 2)
    assert ep["detect_after_pitch"] == 1                            # one pitch (2 mm) slid at row 3
    assert ep["slid_mm"] == 4.0 and m["slid_mm"] == 4.0
    assert m["ratio"] == pytest.approx(1.2) and not m["dropped"]


def test_stuck_parts_on_hand_made_rows():
    """Onset -> stuck again split into detection, the law's raise, the jaw force that stops the
    slide (N >= min_hold_n mu_s / mu_k) and the stop, from rows written by hand; an episode that
    stopped before the centre raised has no parts."""
    from grasp import stuck_parts

    def row(k, slipping=False, slid=0.0, det=False, normal=6.0, least=5.0, flags=()):
        return (k, "lift", normal, least, slipping, slid, False, False, normal, det, True, flags, "stick")
    case = Case(index=0, mass_kg=0.5, mu_s=0.5, mu_k=0.4, accel_m_s2=2.0, disturbance="none", disturb_at_s=0.0,
                load_kg=0.0, shake_m_s2=0.0, shake_hz=0.0, pitch_mm=2.0, fragile=False, max_force_n=None, grasp_n=6.0)
    # stop force: 5 N x 0.5 / 0.4 = 6.25 N
    rows = [row(0), row(1, True, 0.1), row(2, True, 0.5, det=True, flags=("slip_raise",)),
            row(3, True, 1.2, det=True, normal=6.2), row(4, True, 1.8, det=True, normal=6.25),
            row(5, True, 2.0, normal=9.0), row(6, False, 2.0, normal=12.0)]
    parts = stuck_parts(rows, 1, 6, 2, case, 0.01)
    assert parts["parts"] == [1, 0, 2, 2] and not parts["self_stopped"] and parts["raises"] == 1
    assert parts["slid_at_detect_mm"] == pytest.approx(0.1)   # the step the detecting cycle sampled
    assert parts["onset_accel_m_s2"] == pytest.approx(2 * 0.1e-3 / 0.01 ** 2)
    # the law held the raise back (settle) until row 3: detect -> raise 1 cycle
    held = [r if r[0] != 2 else row(2, True, 0.5, det=True) for r in rows]
    held[3] = row(3, True, 1.2, det=True, normal=6.2, flags=("slip_raise",))
    assert stuck_parts(held, 1, 6, 2, case, 0.01)["parts"] == [1, 1, 1, 2]
    # stopped before any raise: no parts
    quiet = [row(0), row(1, True, 0.1), row(2, True, 0.2), row(3, False, 0.2, det=True)]
    assert stuck_parts(quiet, 1, 3, 3, case, 0.01) == {"parts": None, "self_stopped": True, "raises": 0,
                                                       "slid_at_detect_mm": pytest.approx(0.2),
                                                       "onset_accel_m_s2": pytest.approx(2.0)}


def test_bench_contacts_lie_within_one_pitch_and_leave_the_other_draws_alone():
    """bench/grasp.py --contact random: each grasp's contact centre uniform over one pitch about
    the pads' middle, [-p/2, p/2), drawn from its own generator - the grasps are otherwise those of
    --contact centred (offset 0); the case's scene carries it as [grasp] grip_at_mm, and
    bench/grasp_drive.py's drive as 0x6087 (N/s -> ‰/s of the rated force) and force_lag_ms."""
    import dataclasses

    import numpy as np

    from grasp import _base, case_scene, make_case, place_contacts

    def cases(how):
        rng = np.random.default_rng(23)
        return place_contacts([make_case(rng, i) for i in range(200)], 23, how)

    centred, moved = cases("centred"), cases("random")
    assert all(c.contact_offset_mm == 0.0 for c in centred)
    offsets = np.array([c.contact_offset_mm / c.pitch_mm for c in moved])
    assert ((-0.5 <= offsets) & (offsets < 0.5)).all()
    assert offsets.min() < -0.4 and offsets.max() > 0.4 and abs(np.mean(offsets)) < 0.1   # spread over the pitch
    assert [dataclasses.replace(c, contact_offset_mm=0.0) for c in moved] == centred
    base = _base()
    scene = case_scene(base, moved[0], "decision", drive=(2000.0, 5.0))
    assert scene.grasp.grip_at == pytest.approx(base.grasp.grip_at + moved[0].contact_offset_mm)
    assert scene.gripper.torque_slope_permille_s == 2000 * 1000 / base.gripper.rated_force_n == 20000
    assert scene.grasp.force_lag_ms == 5.0
    assert case_scene(base, centred[0], "decision").grasp.grip_at == base.grasp.grip_at == 20.0
    assert scene.bus.sync_period_ms == base.bus.sync_period_ms == 10.0   # no SYNC given: the base scene's
    fast = case_scene(base, moved[0], "raw", drive=(500.0, 20.0, 5.0))
    assert (fast.bus.sync_period_ms, fast.bus.mode) == (5.0, "raw")


def test_bench_variant_sync_period_steps_world_drive_and_centre_by_it():
    """bench/grasp_drive.py --syncs: a case's scene at a 5 ms SYNC runs the same task (its phases'
    seconds) in twice the cycles, and the drive's communication cycle period 0x1006 is 5,000 us."""
    import numpy as np

    from grasp import _base, case_scene, make_case
    from grasp_sim import OfflineDrive, run_grasp

    case = make_case(np.random.default_rng(23), 0)
    runs = {}
    for sync in (10.0, 5.0):
        scene = case_scene(_base(), case, "decision", drive=(500.0, 20.0, sync))
        assert OfflineDrive(scene).drive.objects.read(0x1006) == int(sync * 1000)
        runs[sync] = run_grasp(scene, "decision")["rows"]
    assert not any(r[6] for r in runs[10.0] + runs[5.0])          # neither dropped the object
    # each timed phase of the task: the same seconds, twice the cycles (up to a phase edge's cycle)
    for phase in ("approach", "close", "lift", "hold", "place"):
        cycles = {sync: sum(1 for r in rows if r[1] == phase) for sync, rows in runs.items()}
        assert cycles[10.0] > 10 and abs(cycles[5.0] - 2 * cycles[10.0]) <= 1, (phase, cycles)


def test_grasp_drive_prices_each_pad_layouts_bus_and_flags_a_cycle_that_does_not_fit():
    """bench/grasp_drive.py's bus table: per pad layout and SYNC period, every one-taxel node's PDO
    at its worst-case stuffed length (Davis et al. 2007, eq. 2, 11-bit identifier:
    8n + 47 + floor((34 + 8n - 1) / 4) bits with the 3-bit intermission) plus the loop's own
    frames, over the period's bits at the scene's bit rate; the raw 1.5 mm pads at a 5 ms SYNC do
    not fit (flagged), at 10 ms they do."""
    from grasp import _base
    from grasp_drive import layout_bus_share, render_bus
    from grasp_layout import pad_rows
    from grasp_sim import BitCounter

    base = _base()
    node, bitrate = base.gripper.node_id, base.bus.bitrate
    for pitch, mode, n_bytes, sync in ((1.5, "raw", 4, 5.0), (2.0, "decision", 1, 10.0), (4.0, "raw", 4, 5.0)):
        frame = 8 * n_bytes + 47 + (34 + 8 * n_bytes - 1) // 4
        want = (len(pad_rows(pitch)) * frame + BitCounter.loop_bits(node)) / (sync * 1e-3 * bitrate)
        assert layout_bus_share(pitch, mode, sync, bitrate, node) == pytest.approx(want, rel=1e-12)
    assert len(pad_rows(1.5)) == 68 and layout_bus_share(1.5, "raw", 5.0, bitrate, node) > 1
    assert layout_bus_share(1.5, "raw", 10.0, bitrate, node) < 1
    table, over = render_bus([(500.0, 20.0, 10.0), (500.0, 20.0, 5.0)], "raw", bitrate, node)
    assert any(line.startswith("raw: the 1.5 mm pads at a 5 ms SYNC need") for line in over)
    assert not any("10 ms SYNC" in line for line in over)
