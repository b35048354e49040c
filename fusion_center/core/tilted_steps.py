"""The steps of the tilted DP (:func:`.tilted_dp.lattice_law_rows`): one taxel added to the
law of (state, start label, x) as a few in-place vector operations on state rows.

A step maps the rows of the states (u_(i-1), u_i) = (a, b) to those of (b, c): row (b, c) at x +
shift[a, b, c] receives P_i(c) e^(theta s) times row (a, b) at x (theta the tilt of the
arithmetic, 0 while untilted; every weight divided by the step's largest, ``wmax``). Two things
make it cheaper than one vector addition per pair of inputs:

* merged states: where shift[0, b, c] = shift[1, b, c] for both c (the taxel after an absent one
  on {0,1}; every b with one zero weight on {-1,+1}), the rows (0, b) and (1, b) have the same
  future and are carried as their sum, one row (b, c) -> (., c) summed over b where c is such a
  b (the last step keeps the four states: the end labels need them). Their future weights are
  equal, so the trimming's error bound (the spread of the future weights) is unchanged;
* in-place accumulation: each new row is accumulated in a row whose old content is one of its
  terms (unmoved, and not read after) or in a spare row (one copy): y += x by numpy, y += w x
  (a ratio of tilts) by BLAS daxpy; the branch factor, where it is not 1, multiplies a spare's
  copy and the weights of its other terms, or a row accumulated in place at the end. The rows
  are renamed instead of moved; the renaming cycles with a short period, so the views are
  formed once per block and phase.

The order of the new rows and their accumulators is chosen per lattice form (fewest copies), and
every term of a row is added with a relative weight <= 1 (the heaviest term first), then the
row is multiplied by its branch factor, <= e: ``wmax`` is the largest transition weight, or the
factor of the rows that are most often not multiplied where that is within e of it (as the
previous steps did). A value grows by at most 3 e per step (three terms), < 2^100 over a block
of 32, inside the doubles' headroom above 2^SCALE_BITS (:mod:`.tilted_dp`). Rounding: every
operation adds positive terms or multiplies by a positive factor (relative error <= 2 ulp per
step and value, as before).
"""

from __future__ import annotations

import itertools
import math

import numpy as np
from scipy.linalg.blas import daxpy

MERGED = 2
"""Key (MERGED, b): the sum of the rows (0, b) and (1, b)."""
AXPY_CHUNK = 10000
"""daxpy is called on at most this many elements at a time: OpenBLAS runs longer vectors
(> 10000, measured) on several threads, whose waiting costs far more than it saves on a shared
machine (a call at 3*10^4 taxels took 12 s to minutes instead of 4 s)."""


def merged_bs(shift: np.ndarray) -> tuple[int, ...]:
    """The b whose states (0, b) and (1, b) move alike (shift[0, b, c] = shift[1, b, c] for both c)."""
    return tuple(b for b in (0, 1) if all(int(shift[0, b, c]) == int(shift[1, b, c]) for c in (0, 1)))


def state_keys(merged: tuple) -> list:
    """The rows carried between steps: (MERGED, b) for a merged b, else (0, b) and (1, b)."""
    return [k for b in (0, 1) for k in (((MERGED, b),) if b in merged else ((0, b), (1, b)))]


def _outputs(shift: np.ndarray, in_keys: list, out_keys: list) -> list:
    """Per new row: (key, c, terms), terms [(input key, shift)]; a merged output (MERGED, c)
    sums the terms of (0, c) and (1, c)."""
    out = []
    for ok in out_keys:
        bs = (0, 1) if ok[0] == MERGED else (ok[0],)
        c = ok[1]
        terms = [(ik, int(shift[0 if ik[0] == MERGED else ik[0], ik[1], c])) for ik in in_keys if ik[1] in bs]
        out.append((ok, c, terms))
    return out


def build_plan(shift: np.ndarray, in_keys: list, out_keys: list, sign: int) -> list:
    """The operations of one step: [(out key, c, s_ref, accumulator, ops)] in execution order;
    accumulator ("in", input key) -- accumulated in place in that input's row -- or ("spare", j);
    ops [(kind, input key, shift, relative weight)], kind "copy" (the first term into a spare) or
    "add". ``sign`` is the sign of the arithmetic's tilt: a term's weight is e^(theta s), so the
    heaviest term (largest sign * s) is the accumulator's first; the others are added with
    weights e^(theta (s - s_ref)) <= 1, given as the shift difference (resolved per tilt)."""
    outs = _outputs(shift, in_keys, out_keys)
    best = None
    for order in itertools.permutations(range(len(outs))):
        plan = []
        spares = 0
        for pos, k in enumerate(order):
            key, c, terms = outs[k]
            later = {ik for j in order[pos + 1:] for ik, _ in outs[j][2]}
            heavy = max(sign * s for _, s in terms)
            inplace = [ik for ik, s in terms if s == 0 and sign * s == heavy and ik not in later]
            if inplace:
                ik0 = inplace[0]
                rest = [(ik, s) for ik, s in terms if ik != ik0]
                ops = [("add", ik, s, s) for ik, s in rest]
                plan.append((key, c, 0, ("in", ik0), ops))
            else:
                first = max(terms, key=lambda t: sign * t[1])
                rest = [t for t in terms if t is not first]
                ops = [("copy", first[0], first[1], 0)] + [("add", ik, s, s - first[1]) for ik, s in rest]
                plan.append((key, c, first[1], ("spare", spares), ops))
                spares += 1
        cost = (spares, sum(len(p[4]) for p in plan))
        if best is None or cost < best[0]:
            best = (cost, plan)
    return best[1]


class StepRunner:
    """The state rows of one run of the tilted DP and its steps. ``store`` holds one row per
    slot (columns x labels, labels innermost, flattened); ``keys`` maps each state key to its
    slot. Columns j of the buffer stand for x = j - pad + xmin (:func:`.tilted_dp.lattice_law_rows`)."""

    def __init__(self, lat, pi: np.ndarray, size: int, n_labels: int):
        self.shift = lat.shift
        self.n = pi.size
        self.L = n_labels
        merged = merged_bs(lat.shift) if self.n > 2 else ()
        self.mid = state_keys(merged)
        self.last = [(a, b) for a in (0, 1) for b in (0, 1)]
        with np.errstate(divide="ignore"):
            self.logp = (np.log1p(-pi), np.log(pi))
        plans = {s: (build_plan(lat.shift, self.mid, self.mid, s), build_plan(lat.shift, self.mid, self.last, s))
                 for s in (-1, 0, 1)}
        self.plans = plans
        n_spares = max(sum(1 for p in plan if p[3][0] == "spare") for pair in plans.values() for plan in pair)
        n_slots = max(len(self.mid), 4) + n_spares
        self.store = np.zeros((n_slots, size * n_labels))
        self.rows = list(self.store)  # 1-D views, one per slot (cheaper to slice)
        self.keys = {k: j for j, k in enumerate(self.mid if self.n > 2 else self.last)}
        self.spares = list(range(len(self.keys), n_slots))
        self.theta = None

    # ---------------------------------------------------------------- set-up
    def put(self, a: int, b: int, j: int, label: int, value: float) -> None:
        """Adds an initial value (state (a, b) after the first two taxels) at column j."""
        key = (a, b) if (a, b) in self.keys else (MERGED, b)
        self.store[self.keys[key], j * self.L + label] += value

    def arithmetic(self, theta: float):
        """Adopts the arithmetic tilted by ``theta`` (0: untilted) from the next step on: per
        step the ln of the largest transition weight and of the least total weight a state
        passes on (both as in :func:`.tilted_dp.lattice_law_rows`), the branch factors of the
        plans' rows, and the renaming cycle from the current slots."""
        shift, logp = self.shift, self.logp
        self.theta = theta
        sign = 0 if theta == 0.0 else (1 if theta > 0 else -1)
        self.plan_mid, self.plan_last = self.plans[sign]
        trans = [logp[c] + theta * int(shift[a, b, c]) for a in (0, 1) for b in (0, 1) for c in (0, 1)]
        top = np.max(trans, axis=0)
        # the weights are divided by the largest transition weight, or by a row's factor within e
        # of it where that spares more multiplications (the rows with that factor are not
        # multiplied: a step then multiplies a value by at most 3 e, a block by < 2^100)
        groups: dict = {}
        for _, c, s_ref, _, _ in self.plan_mid:
            groups[(c, s_ref)] = groups.get((c, s_ref), 0) + 1
        log_wmax = top.copy()
        best = np.zeros(top.shape)
        for (c, s_ref), count in sorted(groups.items(), key=lambda kv: kv[1]):
            lw = logp[c] + theta * s_ref
            take = (lw >= top - 1.0) & (count > best)
            log_wmax = np.where(take, lw, log_wmax)
            best = np.where(take, count, best)
        least = np.min([np.logaddexp(trans[4 * a + 2 * b], trans[4 * a + 2 * b + 1]) for a in (0, 1) for b in (0, 1)],
                       axis=0) - log_wmax

        def factors(plan):
            out = []
            for _, c, s_ref, _, ops in plan:
                f = np.exp(logp[c] + theta * s_ref - log_wmax)
                out.append(f.tolist() if np.any(f[2:] != 1.0) else None)  # None: never multiplied
            return out

        self.fac_mid, self.fac_last = factors(self.plan_mid), factors(self.plan_last)
        self._cycle()
        return log_wmax, least.tolist()

    def _step_map(self, keys: dict, spares: list, plan: list) -> tuple[dict, list]:
        """The slots after a step: each new row in its accumulator's slot; the spares, the
        input slots not reused and the spares not used, in a fixed order (so the renaming of the
        middle steps is a permutation of these roles and cycles)."""
        new = {}
        used = set()
        for key, _, _, acc, _ in plan:
            new[key] = keys[acc[1]] if acc[0] == "in" else spares[acc[1]]
            used.add(new[key])
        freed = [keys[k] for k in sorted(keys) if keys[k] not in used] + [j for j in spares if j not in used]
        return new, freed

    def _cycle(self) -> None:
        """The renaming cycle of the middle steps from the current slots: phases [(keys,
        spares, resolved ops)], resolved ops [(kind, destination slot, source slot, shift,
        weight or factor row)]."""
        phases = []
        keys, spares = dict(self.keys), list(self.spares)
        while True:
            phases.append((keys, spares, self._resolve(keys, spares, self.plan_mid, self.fac_mid)))
            keys, spares = self._step_map(keys, spares, self.plan_mid)
            if keys == phases[0][0] and spares == phases[0][1]:
                break
            if len(phases) > 64:
                raise AssertionError("the renaming of the rows does not cycle")
        self.phases = phases
        self.phase = 0

    def _resolve(self, keys: dict, spares: list, plan: list, facs: list) -> list:
        ops = []
        for (key, c, s_ref, acc, terms), fac in zip(plan, facs):
            dst = keys[acc[1]] if acc[0] == "in" else spares[acc[1]]
            # a spare's branch factor goes into its copy and the weights of its other terms (no
            # multiplication of its own); an accumulator in place is multiplied at the end
            fold = fac is not None and acc[0] == "spare"
            for kind, ik, s, d in terms:
                w = math.exp(self.theta * d) if self.theta else 1.0
                if kind == "copy":
                    ops.append(("mulcopy", dst, keys[ik], s, fac) if fold else ("copy", dst, keys[ik], s, 1.0))
                elif fold:
                    ops.append(("faxpy", dst, keys[ik], s, (w, fac)))
                else:
                    ops.append(("add" if w == 1.0 else "axpy", dst, keys[ik], s, w))
            if fac is not None and not fold:  # a row never multiplied: no operation
                ops.append(("scale", dst, None, 0, fac))
        return ops

    # ---------------------------------------------------------------- steps
    def _views(self, ops: list, lo: int, hi: int) -> list:
        L, rows = self.L, self.rows
        n = (hi - lo) * L
        out = []
        for kind, dst, src, s, w in ops:
            if kind == "axpy":
                for c0 in range(0, n, AXPY_CHUNK):
                    out.append((3, rows[dst], rows[src], (min(AXPY_CHUNK, n - c0), w, (lo - s) * L + c0, 1,
                                                          lo * L + c0, 1)))
            elif kind == "faxpy":
                for c0 in range(0, n, AXPY_CHUNK):
                    out.append((6, rows[dst], rows[src], (min(AXPY_CHUNK, n - c0), w[0], w[1], (lo - s) * L + c0,
                                                          lo * L + c0)))
            elif kind == "scale":
                out.append((4, rows[dst][lo * L:hi * L], None, w))
            else:
                out.append(({"copy": 0, "add": 2, "mulcopy": 5}[kind], rows[dst][lo * L:hi * L],
                            rows[src][(lo - s) * L:(hi - s) * L], w))
        return out

    @staticmethod
    def _step(ops: list, i: int) -> None:
        """One taxel (index i) by the resolved operations with their views."""
        for kind, y, x, arg in ops:
            if kind == 2:
                y += x
            elif kind == 4:
                f = arg[i]
                if f != 1.0:
                    y *= f
            elif kind == 0:
                np.copyto(y, x)
            elif kind == 5:
                f = arg[i]
                if f == 1.0:
                    np.copyto(y, x)
                else:
                    np.multiply(x, f, out=y)
            elif kind == 6:
                n, w, fac, offx, offy = arg
                daxpy(x, y, n, w * fac[i], offx, 1, offy, 1)
            else:
                n, w, offx, incx, offy, incy = arg
                daxpy(x, y, n, w, offx, incx, offy, incy)

    def run(self, start: int, end: int, lo: int, hi: int) -> None:
        """Taxels start .. end - 1 added over the window [lo, hi) of buffer columns (it covers
        every step's live range: zero outside the live columns)."""
        mid_end = min(end, self.n - 1)
        if mid_end > start:
            views = [self._views(ops, lo, hi) for _, _, ops in self.phases]
            phase, period = self.phase, len(self.phases)
            step = self._step
            for i in range(start, mid_end):
                step(views[phase], i)
                phase = (phase + 1) % period
            self.phase = phase
            self.keys, self.spares = dict(self.phases[phase][0]), list(self.phases[phase][1])
        if end == self.n and end - 1 >= start:  # the last taxel: the four states again
            i = self.n - 1
            ops = self._resolve(self.keys, self.spares, self.plan_last, self.fac_last)
            self._step(self._views(ops, lo, hi), i)
            self.keys, self.spares = self._step_map(self.keys, self.spares, self.plan_last)

    # ---------------------------------------------------------------- the rows
    def slots(self) -> list:
        return sorted(self.keys.values())

    def column_sums(self, lo: int, hi: int) -> np.ndarray:
        """Per column of [lo, hi): the sum over the state rows and labels (a new array)."""
        L = self.L
        slots = self.slots()
        acc = self.store[slots[0], lo * L:hi * L].copy()
        for j in slots[1:]:
            acc += self.store[j, lo * L:hi * L]
        if L == 1:
            return acc
        acc = acc.reshape(hi - lo, L)
        cols = acc[:, 0].copy()
        for ls in range(1, L):
            cols += acc[:, ls]
        return cols

    def window(self, lo: int, hi: int) -> np.ndarray:
        """The state rows over [lo, hi) as a (rows, columns, labels) copy."""
        return self.store[self.slots(), lo * self.L:hi * self.L].reshape(-1, hi - lo, self.L)

    def set_window(self, lo: int, hi: int, values: np.ndarray) -> None:
        self.store[self.slots(), lo * self.L:hi * self.L] = values.reshape(len(self.keys), -1)

    def scale(self, lo: int, hi: int, factor: float) -> None:
        for j in self.slots():
            self.store[j, lo * self.L:hi * self.L] *= factor

    def zero(self, lo: int, hi: int) -> None:
        """Columns [lo, hi) set to 0 in every slot (spares included)."""
        self.store[:, lo * self.L:hi * self.L] = 0.0

    def row(self, a: int, b: int, ls: int, lo: int, hi: int) -> np.ndarray:
        """Final state (a, b), start label ls, columns [lo, hi) (after the last taxel)."""
        return self.store[self.keys[(a, b)], lo * self.L + ls:hi * self.L:self.L]
