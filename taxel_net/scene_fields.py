"""The field checks of the scene loader (:mod:`taxel_net.scene`) and of the tables it delegates
(:mod:`taxel_net.gripper`): each bad value raises :class:`taxel_net.errors.SceneError` naming the
file, the dotted field, the value and what is allowed - one line."""

from __future__ import annotations

import math

from taxel_net.errors import SceneError


class Where:
    """Where a value comes from: the file and how a key is named in messages."""

    def __init__(self, path: str, prefix: str = "", csv_line: int | None = None):
        self.path = path
        self.prefix = prefix
        self.csv_line = csv_line

    def name(self, key: str) -> str:
        if self.csv_line is not None:
            return f"line {self.csv_line}, column {key}"
        return f"{self.prefix}.{key}" if self.prefix else key

    def fail(self, key: str, value: object, problem: str):
        raise SceneError(self.path, self.name(key), value, problem)


def is_int(v) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def is_num(v) -> bool:
    return (isinstance(v, (int, float))) and not isinstance(v, bool)


def table(w: Where, key: str, value, allowed: tuple[str, ...], of: str = "") -> dict:
    """A sub-table: must be a dict whose keys are all in ``allowed`` (``of``: whose keys these
    are, when the table's kind decides them, e.g. "a 'hold' phase")."""
    if not isinstance(value, dict):
        w.fail(key, value, "must be a table")
    sub = Where(w.path, w.name(key) if key else w.prefix)
    for k in value:
        if k not in allowed:
            sub.fail(k, value[k], f"unknown key{' for ' + of if of else ''} (allowed: {', '.join(allowed)})")
    return value


def integer(w: Where, key: str, v, lo: int | None = None, hi: int | None = None, allowed: str = "") -> int:
    if not is_int(v):
        w.fail(key, v, "must be an integer")
    if (lo is not None and v < lo) or (hi is not None and v > hi):
        w.fail(key, shown_number(v), allowed or f"must lie in {lo}..{hi}")
    return v


def shown_number(v):
    """``v`` for a one-line message: an integer of more than 20 digits as its first digits and length."""
    if is_int(v) and len(str(abs(v))) > 20:
        text = str(v)
        return f"{text[:12]}... ({len(text.lstrip('-'))} digits)"
    return v


def number(w: Where, key: str, v, lo: float | None = None, hi: float | None = None,
           lo_open: bool = False, hi_open: bool = False) -> float:
    if not is_num(v):
        w.fail(key, v, "must be a number")
    try:
        v = float(v)
    except OverflowError:  # an integer beyond any float (TOML integers are unbounded)
        w.fail(key, shown_number(v), "must be finite")
    if not math.isfinite(v):
        w.fail(key, v, "must be finite")
    bad = ((lo is not None and (v <= lo if lo_open else v < lo))
           or (hi is not None and (v >= hi if hi_open else v > hi)))
    if bad:
        lb = "-inf" if lo is None else f"{lo:g}"
        ub = "inf" if hi is None else f"{hi:g}"
        w.fail(key, v, f"must lie in {'(' if lo_open or lo is None else '['}{lb}, "
                       f"{ub}{')' if hi_open or hi is None else ']'}")
    return v


def boolean(w: Where, key: str, v) -> bool:
    if not isinstance(v, bool):
        w.fail(key, v, "must be true or false")
    return v


def string(w: Where, key: str, v, choices: tuple[str, ...] | None = None) -> str:
    if choices is not None and (not isinstance(v, str) or v not in choices):
        w.fail(key, v, f"must be one of {', '.join(choices)}")  # a non-string too: what it may be
    if not isinstance(v, str):
        w.fail(key, v, "must be a string")
    return v


def array(w: Where, key: str, v, length: int | None = None) -> list:
    if not isinstance(v, list):
        w.fail(key, v, "must be an array")
    if length is not None and len(v) != length:
        w.fail(key, v, f"must have {length} entries (has {len(v)})")
    return v


def distinct_strings(w: Where, key: str, raw, choices: tuple[str, ...] | None = None) -> list[str]:
    """An array of strings (each one of ``choices`` when given), none listed twice."""
    out: list[str] = []
    for i, v in enumerate(array(w, key, raw)):
        string(w, f"{key}[{i}]", v, choices)
        if v == "":
            w.fail(f"{key}[{i}]", v, "must not be empty")
        if v in out:
            w.fail(f"{key}[{i}]", v, "listed twice")
        out.append(v)
    return out
