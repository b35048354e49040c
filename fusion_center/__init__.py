"""taxel-can fusion centre: HEBTEM decision fusion for a CANopen taxel network.

Public API (``docs/api.md``); internal module paths are free to change, these names are not.
The node twins on a private virtual bus, the centre fusing 20 SYNC cycles, the core directly::

    import numpy as np

    import fusion_center as fc
    import node_sim

    scene = fc.load_scene("scenes/matrix57.toml")                       # -> fc.Scene
    channels = [f"api-example-{name}" for name in scene.bus.channels]   # python-can virtual channels
    rig = node_sim.Rig(scene, interface="virtual", channel=channels)    # 57 CANopen node twins
    with fc.FusionService(scene, interface="virtual", channels=channels) as centre:
        rig.start()
        centre.boot()                                                   # NMT, SDO configuration
        summary = centre.run(20)                                        # -> fc.RunSummary
    rig.stop()
    decisions = [record["decision"] for record in centre.records]       # "H1", "H0" or "undecided"
    threshold = fc.core.additive_threshold(57, 0.9, 0.03)               # eq 17
    mc = fc.simulate(scene, 2_000, np.random.default_rng(1), central=False)  # Monte Carlo, every rule

Layout: :mod:`.core` (pure functions of the method), :mod:`.service` (the CANopen master on
python-can), :mod:`.commands` (the ``fusion-center`` CLI), :mod:`.evaluation` (the core
applied to a scene), :mod:`.stages` (what a scene needs and supports), :mod:`.report` (bandwidth, report, plots).
Shared with the node twins: the package ``taxel_net`` (scene, errors, CAN frame helper).
Names are imported on first use: ``import fusion_center.core.rules`` stays free of CAN.
"""

from __future__ import annotations

import lazy_loader

from taxel_net.errors import ParameterError, SceneError, UsageError  # noqa: F401  (light: no CAN)
from taxel_net.scene import Scene, load_scene  # noqa: F401

__version__ = "0.1.0"

# the rest is imported on first use (PEP 562): ``import fusion_center.core.rules`` loads no CAN
_getattr, _dir, _lazy = lazy_loader.attach(__name__, submodules=["core"], submod_attrs={
    "service": ["FusionService", "RunSummary", "ZenohPublisher", "replay_trace", "read_records"],
    "stages": ["plan_stages", "StagePlan"],
    "evaluation": ["simulate"],
})
__getattr__ = _getattr
__all__ = sorted(set(_lazy) | {"ParameterError", "SceneError", "UsageError", "Scene", "load_scene", "__version__"})


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
