"""Simulated physics (eqs 1-4 observation model): ground truth, footprints, signals, noise, faults."""

import subprocess
import sys
from math import erfc, sqrt
from pathlib import Path

import numpy as np
import pytest

from taxel_net.errors import ParameterError
from taxel_net.scene import load_scene
from node_sim import physics

ROOT = Path(__file__).resolve().parent.parent

SCENE = """
[scene]
name = "phys"
seed = 11
cycles = 20

[kinds.R]
zeta_mv = 1.0
noise_mv = 0.5
noise_sigma_mv = 0.25
signal_mv = 4.0

[[taxels]]
node_id = 1
kind = "R"
x = 0.0
y = 0.0

[[taxels]]
node_id = 2
kind = "R"
x = 10.0
y = 0.0
slope = 2.0
intercept = -0.5

[[taxels]]
node_id = 3
kind = "R"
x = 20.0
y = 0.0
noise_sigma_mv = 0.0

[object]
{object}

[fusion]
tuple = "pm1"
{extra}
"""


def scene(tmp_path, obj, extra=""):
    p = tmp_path / "s.toml"
    p.write_text(SCENE.format(object=obj, extra=extra))
    return load_scene(p)


def test_ground_truth_intervals(tmp_path):
    s = scene(tmp_path, 'model = "small"\nradius = 1.0\npresent = [[2, 5], [8, 9]]')
    assert physics.truth_batch(s, np.arange(11)).tolist() == [
        False, False, True, True, True, False, False, False, True, False, False]
    assert physics.object_present(s, 4) and not physics.object_present(s, 5)


def test_footprints(tmp_path):
    small = scene(tmp_path, 'model = "small"\nx = 0.0\ny = 0.0\nradius = 10.0\npresent = [[0, 5]]')
    assert physics.contact_mask(small, 1).tolist() == [True, True, False]   # distance 10 is inside
    assert physics.contact_mask(small, 5).tolist() == [False, False, False]  # not present
    point = scene(tmp_path, 'model = "point"\nx = 5.0\ny = 3.0\npresent = [[0, 5]]')
    assert physics.contact_mask(point, 0).tolist() == [True, True, False]   # equidistant: both
    point = scene(tmp_path, 'model = "point"\nx = 14.0\ny = 0.0\npresent = [[0, 5]]')
    assert physics.contact_mask(point, 0).tolist() == [False, True, False]
    none = scene(tmp_path, 'model = "none"\npresent = [[0, 5]]')
    assert not physics.contact_mask(none, 1).any()


def test_slipping_centre_moves_from_onset(tmp_path):
    s = scene(tmp_path, 'model = "slipping"\nx = 0.0\ny = 0.0\nradius = 3.0\npresent = [[0, 100]]\n'
                        'velocity = [2.0, 0.5]\nslip_onset_cycle = 4')
    assert physics.object_centre(s, 0) == (0.0, 0.0)
    assert physics.object_centre(s, 4) == (0.0, 0.0)
    assert physics.object_centre(s, 9) == pytest.approx((10.0, 2.5))
    # centre (2k, k/2) after k steps: taxel at x = 10 is within 3 only for k = 4, 5 (centre x 8..12
    # with y 2..3 -> distance sqrt(4 + 4) = 2.83 at k = 4, 2.5 at k = 5, 3.6 at k = 6 -> only 4, 5)
    mask = np.array([physics.contact_mask(s, c) for c in range(4, 16)])
    assert (np.flatnonzero(mask[:, 1]) + 4).tolist() == [8, 9]       # k = 4, 5
    assert (np.flatnonzero(mask[:, 0]) + 4).tolist() == [4, 5]       # centre (0,0), (2,0.5)


def test_signal_calibrated_taxel_under_tangential_force(tmp_path):
    s = scene(tmp_path, 'model = "large"\nradius = 50.0\npresent = [[0, 5]]\ntangential_force = 1.5')
    # taxel 2: m F + c = 2 * 1.5 - 0.5 (eq 23); others the kind's signal_mv
    assert physics.signal_mv(s, 0).tolist() == [4.0, 2.5, 4.0]
    assert physics.signal_mv(s, 7).tolist() == [0.0, 0.0, 0.0]


def test_script_readings_y_and_x(tmp_path):
    y_scene = scene(tmp_path, 'model = "script"\nreadings_mv = [3.0, 0.2, 7.0]\npresent = [[0, 2]]')
    assert physics.signal_mv(y_scene, 0).tolist() == [3.0, 0.2, 7.0]          # S = Y (eq 4)
    x_scene = scene(tmp_path, 'model = "script"\nreadings_mv = [3.0, 0.2, 7.0]\npresent = [[0, 2]]\n'
                              'readings_are = "X"')
    assert physics.signal_mv(x_scene, 0) == pytest.approx([2.5, -0.3, 6.5])   # S = X - N
    # taxel 3 has sigma = 0: its reading is exactly S + N
    assert physics.sample_readings(x_scene, 0)[2] == 7.0
    assert physics.sample_readings(x_scene, 3)[2] == 0.5


def test_readings_follow_the_documented_canonical_stream(tmp_path):
    s = scene(tmp_path, 'model = "small"\nradius = 1.0\npresent = [[2, 5]]')
    for c in (0, 3, 17):
        eps = np.random.default_rng(np.random.SeedSequence([11, c])).standard_normal(3)
        sigma = np.array([0.25, 0.25, 0.0])
        s_i = np.array([4.0, 0.0, 0.0]) if 2 <= c < 5 else np.zeros(3)
        assert physics.sample_readings(s, c) == pytest.approx(s_i + 0.5 + sigma * eps, abs=1e-15)
        assert physics.taxel_reading(s, c, 1) == physics.sample_readings(s, c)[1]
    cycles = np.array([5, 0, 3, 3, 12])
    batch = physics.sample_readings_batch(s, cycles)
    assert np.array_equal(batch, np.stack([physics.sample_readings(s, int(c)) for c in cycles]))


def test_another_process_gets_the_same_readings():
    code = ("import sys; from taxel_net.scene import load_scene; from node_sim import physics;"
            "s = load_scene(sys.argv[1]); print(repr(physics.taxel_reading(s, 42, 17)))")
    path = str(ROOT / "scenes" / "matrix57.toml")
    out = subprocess.run([sys.executable, "-c", code, path], capture_output=True, text=True, check=True)
    s = load_scene(path)
    assert float(out.stdout) == physics.sample_readings(s, 42)[17]


def q_function(z):
    return 0.5 * erfc(z / sqrt(2))


def test_monte_carlo_noise_statistics_match_the_model():
    # absent cycles of matrix57: the local detector's false-alarm rate must be Q(zeta/sigma) per kind
    s = load_scene(ROOT / "scenes" / "matrix57.toml")
    rng = np.random.default_rng(2024)
    cycles = np.zeros(40_000, dtype=np.int64)          # cycle 0: no object
    x = physics.sample_readings_batch(s, cycles, rng)
    noise = np.array([t.noise_mv for t in s.taxels])
    sigma = np.array([t.noise_sigma_mv for t in s.taxels])
    zeta = np.array([t.zeta_mv for t in s.taxels])
    z = (x - noise) / sigma
    assert abs(z.mean()) < 5 / np.sqrt(z.size)
    assert abs(z.std() - 1) < 5 / np.sqrt(2 * z.size)
    kinds = np.array([t.kind for t in s.taxels])
    for k in ("R", "C", "P"):
        sel = kinds == k
        p = q_function(zeta[sel][0] / sigma[sel][0])
        trials = cycles.size * sel.sum()
        hits = np.count_nonzero((x[:, sel] - noise[sel]) >= zeta[sel])
        assert abs(hits - p * trials) < 5 * np.sqrt(trials * p * (1 - p)), k
    # present cycles: contacted uncalibrated C-taxel misses with Phi((zeta - S)/sigma)
    i = 13  # node 14, C at (21, 29), in the footprint, no calibration
    assert physics.contact_mask(s, 50)[i] and s.taxels[i].slope is None
    xp = physics.sample_readings_batch(s, np.full(40_000, 50), rng)[:, i]
    t = s.taxels[i]
    pm = q_function((t.signal_mv - t.zeta_mv) / t.noise_sigma_mv)
    misses = np.count_nonzero(xp - t.noise_mv < t.zeta_mv)
    assert abs(misses - pm * xp.size) < 5 * np.sqrt(xp.size * pm * (1 - pm))


def test_truth_batch_matches_scene_file():
    s = load_scene(ROOT / "scenes" / "matrix57.toml")
    truth = physics.truth_batch(s, np.arange(s.cycles))
    assert truth.sum() == 100 and truth[20] and truth[119] and not truth[19] and not truth[120]


FAULTS = """
[[faults]]
node_id = 1
fault = "stuck"
from_cycle = 3
until_cycle = 6

[[faults]]
node_id = 2
fault = "open_circuit"
from_cycle = 4

[[faults]]
node_id = 3
fault = "silent"
from_cycle = 0
"""


def test_faults(tmp_path):
    p = tmp_path / "f.toml"
    p.write_text(SCENE.format(object='model = "small"\nradius = 1.0\npresent = [[0, 4]]', extra="") + FAULTS)
    s = load_scene(p)
    clean_p = tmp_path / "c.toml"
    clean_p.write_text(SCENE.format(object='model = "small"\nradius = 1.0\npresent = [[0, 4]]', extra=""))
    clean = load_scene(clean_p)
    cycles = np.arange(9)
    x = physics.sample_readings_batch(s, cycles)
    x0 = physics.sample_readings_batch(clean, cycles)
    # stuck: cycles 3, 4, 5 repeat the reading of cycle 3 (object present then: 4 + N + noise)
    assert x[3:6, 0].tolist() == [x0[3, 0]] * 3 and x0[3, 0] > 3
    assert x[[0, 1, 2, 6, 7, 8], 0].tolist() == x0[[0, 1, 2, 6, 7, 8], 0].tolist()
    # open circuit: NaN from cycle 4 on
    assert np.isnan(x[4:, 1]).all() and not np.isnan(x[:4, 1]).any()
    # silent: physics unchanged (the node twin goes quiet)
    assert x[:, 2].tolist() == x0[:, 2].tolist()
    # stuck value ignores the Monte Carlo stream
    xr = physics.sample_readings_batch(s, cycles, np.random.default_rng(1))
    assert xr[4, 0] == x0[3, 0]


@pytest.mark.parametrize("call", [
    lambda s: physics.sample_readings(s, -1),
    lambda s: physics.sample_readings(s, 1.5),
    lambda s: physics.sample_readings_batch(s, np.array([0.5])),
    lambda s: physics.sample_readings_batch(s, [0], rng=42),
    lambda s: physics.taxel_reading(s, 0, 3),
])
def test_bad_arguments(tmp_path, call):
    s = scene(tmp_path, 'model = "none"')
    with pytest.raises(ParameterError):
        call(s)
