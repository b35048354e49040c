"""The rig's gripper drive and grasp world (issue 22).

Gripper drive: a scene with a ``[gripper]`` table gets its CiA 402 drive
(:class:`node_sim.gripper.host.DriveHost`, ``docs/gripper-drive.md``) on that scene channel, if
served: a bus object of its own on the channel (the interface, bit rate and keywords of the
channel's), configured with ``taxel_net.gripper.startup_values`` (the ``[gripper]`` parameters,
0x1017 / 0x1019 / 0x1006 / 0x1016 from ``bus`` and ``master``), booted after the taxel nodes.
:attr:`Rig.gripper` is that host (None without one); the world acts on ``rig.gripper.drive``
inside ``with rig.gripper.lock:``.

Grasp world: a scene with ``[gripper]`` and ``[grasp]`` whose drive's channel this rig serves
(:attr:`Rig.runs_world`) runs :class:`node_sim.world_runner.WorldRunner` beside the drive (its own
clock at the SYNC period); unless a ``reading_source`` is injected the taxels read the world
(``docs/grasp-world.md``), not ``[object]``. :attr:`Rig.world_truth` is its latest step's record,
``on_truth`` / :meth:`Rig.add_truth_callback` get every step's.

:class:`DriveAndWorld` is that part of :class:`~node_sim.rig.Rig` (a mixin).
"""

from __future__ import annotations

import numpy as np

from ..gripper.host import DriveHost
from ..world_runner import WorldRunner, has_world


class DriveAndWorld:
    """The gripper drive and the grasp world of :class:`~node_sim.rig.Rig` (module docstring)."""

    def _init_drive(self, gripper_eds_path, on_truth) -> None:
        # the gripper drive of [gripper] (issue 22): its own bus object on its scene channel
        self.gripper_eds_path = gripper_eds_path
        self.gripper: DriveHost | None = None
        # the grasp world of [gripper] + [grasp] (node_sim.world_runner), where this rig serves the
        # drive's channel: the taxels read it (an injected reading_source still wins)
        self.world: WorldRunner | None = None
        self._truth_callbacks = [on_truth] if callable(on_truth) else list(on_truth or ())
        self.runs_world = has_world(self.scene) and self.scene.gripper.channel in self.served
        if self.runs_world and self._reading_source is None:
            self._reading_source = self._world_readings

    def _stop_drive(self) -> None:
        if self.world is not None:
            self.world.stop()
            self.world = None  # a rig started again runs a new world (with its new drive)
        if self.gripper is not None:
            self.gripper.stop()
            self.gripper = None

    def _start_gripper(self) -> None:
        """The scene's gripper drive, when it has one on a served channel: a
        :class:`~node_sim.gripper.host.DriveHost` on a bus object of its own on that channel
        (the same interface, bit rate and keywords as the channel's), configured with the
        scene's start-up values, booted after the taxel nodes."""
        g = self.scene.gripper
        if g is None or g.channel not in self._channel_at:
            return
        self.gripper = DriveHost.for_scene(self.scene, self.interface, self.channel_names[g.channel],
                                           self._bus_kwargs(), self.gripper_eds_path)
        self.gripper.start()
        if self.runs_world:
            ch = self._channel_at[g.channel]
            self.world = WorldRunner(self.scene, self.gripper.drive, self.gripper.lock,
                                     sync_state=lambda: ch.sync_state,
                                     on_truth=self._truth_callbacks).start()

    def _world_readings(self, cycle: int) -> np.ndarray:
        """The taxels' readings from the grasp world (before it runs: noise only)."""
        world = self.world
        if world is None:
            from .. import physics

            return physics.observe(self.scene, cycle, np.zeros(self.scene.n))
        return world.readings(cycle)

    @property
    def world_truth(self) -> dict | None:
        """The grasp world's latest step (``Truth.as_dict()`` with ``sync_counter`` and ``cycle``,
        ``docs/grasp-world.md``), None before its first step or without a world."""
        return None if self.world is None else self.world.latest

    def add_truth_callback(self, callback) -> None:
        """Call ``callback(record)`` with every later world step's record (in the world's thread)."""
        self._truth_callbacks.append(callback)
        if self.world is not None and callback not in self.world.callbacks:
            self.world.callbacks.append(callback)
