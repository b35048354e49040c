"""What the node twins and the fusion centre share: the scene (the taxel network and the world
it senses), the error types, and the CAN frame helper.

Nothing here imports from ``fusion_center`` or ``node_sim``; both import from here.
"""
