"""The public API without a bus (docs/api.md): a scene, its stage plan, the numerical core,
a Monte Carlo of the scene. Run from the repository root: python3 docs/examples/api_core.py"""

import numpy as np

import fusion_center as fc

scene = fc.load_scene("scenes/matrix57.toml")
print("scene:", scene.name, "taxels:", scene.n, "mode:", scene.bus.mode)

plan = fc.plan_stages(scene)
print("stages run:", plan.run, "skipped:", sorted(plan.skipped))

# the chapter's 57-taxel example (sec. 6.3.1): cells 5, 8, 18, 19, 20, 31, 33 present
u = np.array([1 if i in (5, 8, 18, 19, 20, 31, 33) else -1 for i in range(1, 58)])
print("U_G additive (eq 6):", fc.core.additive(u, "pm1"))
threshold = fc.core.additive_threshold(57, 0.003, 0.473)          # eq 17
print("threshold (eq 17):", threshold.thresholds, "present taxels needed:", threshold.present_counts)
print("SYNC frame bits:", fc.core.frame_bits(0x080), " one-byte TPDO1 of node 5:", fc.core.frame_bits(0x185, [0x01]))
print("contact area (eq 35):", fc.core.contact_area([(11, 16.5), (31, 16.5), (31, 41.5), (11, 66.5), (1, 66.5)]))

try:
    fc.core.additive_threshold(57, 1.5, 0.03)
except fc.ParameterError as exc:                                    # a ValueError
    print("ParameterError:", exc)

mc = fc.simulate(scene, 2_000, np.random.default_rng(1), central=False)
for rule in ("additive", "k-of-n"):
    print(f"{rule}: exact total error {mc.rules[rule].total_error['exact']:.3g}")
