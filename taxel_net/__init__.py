"""What the node twins and the fusion centre share: the scene (the taxel network and the world
it senses), the error types, and the CAN frame helper.

* :mod:`.scene` - the scene model (taxels, bus, object, fusion set-up, faults) and its loader
  (TOML + CSV, ``docs/scene-format.md``);
* :mod:`.errors` - ParameterError, SceneError, UsageError: bad input the user can fix;
* :mod:`.canmsg` - TxMessage, a ``can.Message`` with a cheap deep copy for frames we send.

Nothing here imports from ``fusion_center`` or ``node_sim``; both import from here. Names are
imported on first use: ``import taxel_net.scene`` loads no CAN library.
"""

from __future__ import annotations

import importlib

_EXPORTS = {
    "load_scene": "scene",
    "Scene": "scene",
    "ParameterError": "errors",
    "SceneError": "errors",
    "UsageError": "errors",
    "TxMessage": "canmsg",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str):
    if name not in _EXPORTS:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(importlib.import_module(f"{__name__}.{_EXPORTS[name]}"), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
