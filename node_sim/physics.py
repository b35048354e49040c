"""Simulated physics of a scene: ground truth, contact footprint, signal and noisy readings.

Shared by the node twins (each node samples its own taxel) and the fusion centre's Monte
Carlo (all taxels, many cycles at once). Pure numpy: no CAN, no I/O.

Observation model (chapter sec. 2.1, eqs 1 and 4)::

    H0: X_i = N_i + sigma_i * eps            (object absent, or taxel outside the footprint)
    H1: X_i = S_i + N_i + sigma_i * eps      (taxel inside the footprint while present)

``N_i`` is the taxel's ``noise_mv`` (the node's noise estimate, a constant offset it subtracts,
eq 4), ``sigma_i`` its ``noise_sigma_mv`` and eps ~ N(0, 1) i.i.d. per taxel and cycle.
The node then decides u_i = +1 iff Y_i = X_i - N_i >= zeta_i (eqs 2-3); so the per-taxel
false-alarm probability is Q(zeta/sigma) and the miss probability Phi((zeta - S)/sigma).

Signal S_i of a contacted taxel:

* ``signal_mv`` of the taxel; or, when ``object.tangential_force`` F > 0 and the taxel has a
  calibration (``slope`` m and ``intercept`` c), the calibrated output m F + c (eq 23 / 27a);
* model ``script``: every taxel is "contacted" while present and S_i comes from
  ``object.readings_mv``: with ``readings_are = "Y"`` (default) the readings are the
  noise-filtered outputs Y_i of eq 4, so S_i = readings_i (X_i = Y_i + N_i + sigma_i eps);
  with ``readings_are = "X"`` they are raw observations, so S_i = readings_i - N_i
  (X_i = readings_i + sigma_i eps). Set ``noise_sigma_mv = 0`` to replay readings exactly.

Random numbers (reproducible in any process): the canonical eps of cycle ``c`` is
``np.random.default_rng(np.random.SeedSequence([scene.seed, c])).standard_normal(n)`` — one
generator per cycle, eps[i] for the taxel at fusion index i. A node twin in another process
gets the same X_i by calling ``sample_readings(scene, c)[i]`` (or ``taxel_reading``); no
state is carried between cycles. Passing an explicit ``rng`` (a ``numpy.random.Generator``)
instead draws eps from that generator: fast independent streams for Monte Carlo, not
reproducible by a node twin.

Faults (``scene.faults``, active for from_cycle <= cycle < until_cycle):

* ``stuck``: the taxel repeats its *canonical* reading of ``from_cycle`` (whatever ``rng``);
* ``open_circuit``: the reading is NaN (``OPEN_CIRCUIT_MV``): the local detector decides
  "absent" for NaN and the node twin must flag the fault (EMCY);
* ``silent``: physics returns normal values; the node twin stops transmitting.
"""

from __future__ import annotations

import numpy as np

from taxel_net.errors import ParameterError
from taxel_net.scene import Scene, taxel_index

OPEN_CIRCUIT_MV = float("nan")   # reading of an open-circuit input
_TIE_TOL = 1e-9                  # "point": taxels within this of the minimum distance all count


def _cycles_array(cycles) -> np.ndarray:
    c = np.asarray(cycles)
    if c.ndim != 1 or (c.size and not np.issubdtype(c.dtype, np.integer)):
        raise ParameterError("cycles", cycles, "must be a 1-D array of integer cycle numbers")
    if c.size and c.min() < 0:
        raise ParameterError("cycles", int(c.min()), "cycle numbers must be >= 0")
    return c.astype(np.int64)


def _check_cycle(cycle) -> int:
    if isinstance(cycle, bool) or not isinstance(cycle, (int, np.integer)) or cycle < 0:
        raise ParameterError("cycle", cycle, "must be an integer >= 0")
    return int(cycle)


_ARRAYS_CACHE: dict[int, tuple[Scene, dict[str, np.ndarray]]] = {}
_ARRAYS_CACHE_SIZE = 8


def taxel_arrays(scene: Scene) -> dict[str, np.ndarray]:
    """Per-taxel parameters as float arrays (fusion order); missing values are NaN.

    Built once per scene object (a scene is immutable; 4,096 taxels take ~60 ms, once per SYNC
    too many for a skin rig) and returned read-only."""
    hit = _ARRAYS_CACHE.get(id(scene))
    if hit is not None and hit[0] is scene:
        return dict(hit[1])
    t = scene.taxels

    def col(name):
        a = np.array([np.nan if getattr(x, name) is None else getattr(x, name) for x in t], float)
        a.setflags(write=False)
        return a

    arrays = {name: col(name) for name in ("x", "y", "zeta_mv", "noise_mv", "noise_sigma_mv",
                                           "signal_mv", "slope", "intercept", "grip_factor")}
    if len(_ARRAYS_CACHE) >= _ARRAYS_CACHE_SIZE:
        _ARRAYS_CACHE.pop(next(iter(_ARRAYS_CACHE)))
    _ARRAYS_CACHE[id(scene)] = (scene, arrays)
    return dict(arrays)


# ---------------------------------------------------------------- ground truth and geometry

def truth_batch(scene: Scene, cycles) -> np.ndarray:
    """Ground truth per cycle: True when the cycle lies in any [start, end) of object.present."""
    c = _cycles_array(cycles)
    out = np.zeros(c.shape, dtype=bool)
    for start, end in scene.object.present:
        out |= (c >= start) & (c < end)
    return out


def object_present(scene: Scene, cycle: int) -> bool:
    """Ground truth H1 at ``cycle`` (cycle inside any [start, end) of object.present)."""
    return bool(truth_batch(scene, np.array([_check_cycle(cycle)]))[0])


def centre_batch(scene: Scene, cycles) -> np.ndarray:
    """Contact centre per cycle, shape (m, 2). Model "slipping": the centre moves by
    ``velocity`` per cycle from ``slip_onset_cycle`` on (x0 + v * max(0, c - onset))."""
    c = _cycles_array(cycles)
    o = scene.object
    centre = np.tile(np.array([o.x, o.y], float), (c.size, 1))
    if o.model == "slipping":
        steps = np.maximum(0, c - int(o.slip_onset_cycle or 0)).astype(float)
        centre += steps[:, None] * np.asarray(o.velocity, float)[None, :]
    return centre


def object_centre(scene: Scene, cycle: int) -> tuple[float, float]:
    """Contact centre (x, y) at ``cycle``."""
    x, y = centre_batch(scene, np.array([_check_cycle(cycle)]))[0]
    return float(x), float(y)


def contact_batch(scene: Scene, cycles) -> np.ndarray:
    """Which taxels the object touches, shape (m, n) bool; all False while not present.

    "point": the nearest taxel(s) to the centre (ties within 1e-9 all count);
    "small"/"large"/"slipping": distance to the centre <= radius; "none": nothing;
    "script": every taxel (its reading is given) while present.
    """
    c = _cycles_array(cycles)
    n = scene.n
    present = truth_batch(scene, c)
    model = scene.object.model
    if model == "none":
        return np.zeros((c.size, n), dtype=bool)
    if model == "script":
        return np.repeat(present[:, None], n, axis=1)
    a = taxel_arrays(scene)
    centre = centre_batch(scene, c)
    dist = np.hypot(a["x"][None, :] - centre[:, :1], a["y"][None, :] - centre[:, 1:])
    if model == "point":
        inside = dist <= dist.min(axis=1, keepdims=True) + _TIE_TOL
    else:
        inside = dist <= scene.object.radius
    return inside & present[:, None]


def contact_mask(scene: Scene, cycle: int) -> np.ndarray:
    """Bool mask (n,) of the taxels in the object's footprint at ``cycle`` (False if absent)."""
    return contact_batch(scene, np.array([_check_cycle(cycle)]))[0]


# ---------------------------------------------------------------- signal and readings

def contact_signal(scene: Scene) -> np.ndarray:
    """S_i a taxel shows when contacted (eq 1): signal_mv, m F + c for a calibrated taxel
    under object.tangential_force F > 0 (eq 23), or the script's readings."""
    a = taxel_arrays(scene)
    o = scene.object
    if o.model == "script":
        r = np.asarray(o.readings_mv, float)
        return r if o.readings_are == "Y" else r - a["noise_mv"]
    s = a["signal_mv"].copy()
    if o.tangential_force > 0:
        calibrated = np.isfinite(a["slope"]) & np.isfinite(a["intercept"])
        s[calibrated] = a["slope"][calibrated] * o.tangential_force + a["intercept"][calibrated]
    return s


def signal_batch(scene: Scene, cycles) -> np.ndarray:
    """S_i(cycle), shape (m, n): the contact signal inside the footprint while present, else 0."""
    return np.where(contact_batch(scene, cycles), contact_signal(scene)[None, :], 0.0)


def signal_mv(scene: Scene, cycle: int) -> np.ndarray:
    """S_i at ``cycle``, shape (n,)."""
    return signal_batch(scene, np.array([_check_cycle(cycle)]))[0]


def canonical_eps(scene: Scene, cycle: int) -> np.ndarray:
    """The canonical standard-normal draws eps_i of ``cycle`` (see module docstring)."""
    gen = np.random.default_rng(np.random.SeedSequence([scene.seed, _check_cycle(cycle)]))
    return gen.standard_normal(scene.n)


def _apply_faults(scene: Scene, cycles: np.ndarray, x: np.ndarray) -> np.ndarray:
    if not scene.faults:
        return x
    for f in scene.faults:
        if f.fault == "silent":
            continue
        i = taxel_index(scene, f.node_id, f.channel)
        active = cycles >= f.from_cycle
        if f.until_cycle is not None:
            active &= cycles < f.until_cycle
        if not active.any():
            continue
        if f.fault == "open_circuit":
            x[active, i] = OPEN_CIRCUIT_MV
        else:  # stuck: the canonical reading of from_cycle
            c0 = np.array([f.from_cycle])
            x0 = (signal_batch(scene, c0)[0, i] + scene.taxels[i].noise_mv
                  + scene.taxels[i].noise_sigma_mv * canonical_eps(scene, f.from_cycle)[i])
            x[active, i] = x0
    return x


def sample_readings_batch(scene: Scene, cycles, rng: np.random.Generator | None = None) -> np.ndarray:
    """X_i = S_i + N_i + sigma_i * eps for every cycle and taxel, shape (len(cycles), n).

    ``rng=None``: the canonical per-cycle draws (identical to ``sample_readings`` cycle by
    cycle, reproducible by a node twin anywhere; one generator per cycle, so slower).
    ``rng`` given: one vectorised draw of shape (m, n) from it (Monte Carlo).
    Faults from ``scene.faults`` are applied (stuck / open_circuit).
    """
    c = _cycles_array(cycles)
    a = taxel_arrays(scene)
    n = scene.n
    if rng is None:
        eps = np.empty((c.size, n))
        for j, cyc in enumerate(c):
            eps[j] = canonical_eps(scene, int(cyc))
    else:
        if not isinstance(rng, np.random.Generator):
            raise ParameterError("rng", rng, "must be a numpy.random.Generator or None")
        eps = rng.standard_normal((c.size, n))
    x = signal_batch(scene, c)
    x += a["noise_mv"]
    eps *= a["noise_sigma_mv"]
    x += eps
    return _apply_faults(scene, c, x)


def observe(scene: Scene, cycle: int, signal, held: dict | None = None, eps: np.ndarray | None = None) -> np.ndarray:
    """Readings X_i = S_i + N_i + sigma_i * eps of one SYNC ``cycle`` from a signal ``S`` computed
    elsewhere (the grasp world's, :mod:`node_sim.world.taxels`), with the canonical ``eps`` of the
    cycle and the scene's faults: ``open_circuit`` reads NaN; ``stuck`` repeats the reading the
    taxel had at the first cycle of the fault this function saw - kept in ``held`` (a dict the
    caller keeps across cycles; without it, the reading of the cycle itself).

    Unlike ``sample_readings`` the signal is not a function of the cycle alone, so a stuck taxel
    cannot be recomputed for its ``from_cycle``: it is remembered. ``eps``: the cycle's
    ``canonical_eps``, when the caller computed it ahead (the grasp world does, off the SYNC)."""
    c = _check_cycle(cycle)
    s = np.asarray(signal, dtype=float)
    if s.shape != (scene.n,):
        raise ParameterError("signal", s.shape, f"must hold {scene.n} values (scene order)")
    a = taxel_arrays(scene)
    if eps is None:
        eps = canonical_eps(scene, c)
    x = s + a["noise_mv"] + a["noise_sigma_mv"] * eps
    for f in scene.faults:
        if f.fault == "silent" or not f.active(c):
            continue
        i = taxel_index(scene, f.node_id, f.channel)
        if f.fault == "open_circuit":
            x[i] = OPEN_CIRCUIT_MV
        elif held is not None:
            x[i] = held.setdefault((f.node_id, f.channel, f.from_cycle), float(x[i]))
    return x


def sample_readings(scene: Scene, cycle: int, rng: np.random.Generator | None = None) -> np.ndarray:
    """Readings X_i of every taxel at ``cycle``, shape (n,) (see ``sample_readings_batch``)."""
    return sample_readings_batch(scene, np.array([_check_cycle(cycle)]), rng)[0]


def taxel_reading(scene: Scene, cycle: int, index: int) -> float:
    """Canonical reading X_i of the taxel at fusion index ``index`` (what its node twin sends)."""
    if not 0 <= index < scene.n:
        raise ParameterError("index", index, f"must lie in 0..{scene.n - 1}")
    return float(sample_readings(scene, cycle)[index])
