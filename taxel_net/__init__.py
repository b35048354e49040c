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

import lazy_loader

__getattr__, __dir__, __all__ = lazy_loader.attach(__name__, submod_attrs={
    "scene": ["load_scene", "Scene"],
    "errors": ["ParameterError", "SceneError", "UsageError"],
    "canmsg": ["TxMessage"],
})
