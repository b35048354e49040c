"""Force units used by the force models (chapter sec. 4, 7).

The chapter's calibration lines (eqs 23, 27a, 27b, 36) map millivolts to *some* force unit:
sec. 7.1 prints kgf, sec. 6.2.3.2 prints "units", sec. 7.2 leaves the TBS/LC coefficients
symbolic (eta kgf/mV, M). Inputs of this package are always mV; outputs are in the unit
the calibration maps to, and that unit is carried explicitly (never implied). The only
conversion offered is the exact definition 1 kgf = 9.80665 N (standard gravity, CGPM 1901).
"""

from __future__ import annotations

import numpy as np

from taxel_net.errors import ParameterError

KGF_IN_NEWTON = 9.80665
FORCE_UNITS: tuple[str, ...] = ("N", "kgf")
_TO_NEWTON = {"N": 1.0, "kgf": KGF_IN_NEWTON}


def check_force_unit(unit: str, name: str = "unit") -> str:
    """Return ``unit`` if it is one of :data:`FORCE_UNITS`, else raise ParameterError."""
    if unit not in _TO_NEWTON:
        raise ParameterError(name, unit, f"force unit must be one of {FORCE_UNITS}")
    return unit


def convert_force(value, from_unit: str, to_unit: str):
    """Convert a force (scalar or array) between "N" and "kgf" (1 kgf = 9.80665 N exactly)."""
    check_force_unit(from_unit, "from_unit")
    check_force_unit(to_unit, "to_unit")
    factor = _TO_NEWTON[from_unit] / _TO_NEWTON[to_unit]
    try:
        force = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        raise ParameterError("value", value, "force must be a number or an array of numbers") from None
    return float(force) * factor if force.ndim == 0 else force * factor
