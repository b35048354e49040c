"""The public API on a bus (docs/api.md): the node twins of a scene on a private python-can
virtual bus and the fusion centre fusing 20 SYNC cycles. Run from the repository root:
python3 docs/examples/api_bus.py"""

import fusion_center as fc
import node_sim

scene = fc.load_scene("scenes/matrix57.toml")
channels = [f"api-bus-{name}" for name in scene.bus.channels]      # python-can virtual channels
rig = node_sim.Rig(scene, interface="virtual", channel=channels)   # 57 CANopen node twins
with fc.FusionService(scene, interface="virtual", channels=channels) as centre:
    rig.start()
    missing = centre.boot()                                        # boot-ups, SDO configuration, NMT start
    summary = centre.run(20)                                       # 20 SYNC cycles -> fc.RunSummary
rig.stop()
print("missing at boot:", missing)
print("cycles:", summary.cycles, "records:", summary.records, "SDO writes:", summary.sdo_writes)
record = centre.records[-1]                                        # the decision log, in memory
print("last record:", sorted(record)[:6], "...")
print("ground truth of cycles 0 and 20:", node_sim.physics.object_present(scene, 0),
      node_sim.physics.object_present(scene, 20))
