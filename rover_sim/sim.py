"""The simulator's logic: render what the rover senses, execute the paths it is given.

:class:`RoverSim` takes and returns plain data (no Zenoh): :meth:`render` gives the
:class:`~rovergate.types.SensorFrame` of a step, :meth:`execute` drives a
:class:`~rovergate.types.PlanPath` in the true world and reports what happened.
"""

from __future__ import annotations

import logging

import numpy as np

from rover_sim.rover import RoverBody
from rover_sim.scene import Scene, load_scene
from rover_sim.world import PyBulletWorld
from rovergate.config import MissionConfig
from rovergate.platform import camera_from_base
from rovergate.types import ExecutionReport, PlanPath, Pose, SensorFrame

log = logging.getLogger("rovergate.sim")


class RoverSim:
    """A rover in a true world: depth rendering, kinematic motion, collision reporting."""

    def __init__(self, cfg: MissionConfig, scene: Scene | None = None) -> None:
        self.cfg = cfg
        self.scene = scene or load_scene(cfg.scene.name)
        if cfg.start not in self.scene.starts:
            raise SystemExit(f"error: scene {self.scene.name!r} has no start {cfg.start!r}; "
                             f"choose one of: {', '.join(self.scene.starts)}")
        self.body = RoverBody(self.scene, cfg.rover)
        self.world = PyBulletWorld(self.scene, cfg.sensor, cfg.rover)
        self.state = self.scene.starts[cfg.start]
        self._truth_surface: np.ndarray | None = None

    @property
    def T_map_base(self) -> np.ndarray:
        return self.body.base_pose(*self.state)

    def render(self, step: int) -> SensorFrame:
        """What the rover senses at its current pose."""
        T_base = self.T_map_base
        T_cam = camera_from_base(T_base, self.cfg.sensor)
        self.world.set_rover_pose(T_base)
        depth = self.world.render_depth(T_cam)
        return SensorFrame(step, depth, self.world.intrinsics, Pose.from_matrix(T_cam),
                           Pose.from_matrix(T_base))

    def execute(self, path: PlanPath) -> ExecutionReport:
        """Drive along ``path`` (its poses' x, y and heading); collisions stop the rover."""
        waypoints = [(float(p.position[0]), float(p.position[1]), p.yaw) for p in path.poses]
        if not waypoints:
            return ExecutionReport(path.step, False, 0, self.body.clearance(self.T_map_base),
                                   0.0, 1.0)
        motion = self.body.drive(self.state, waypoints)
        if motion.collided:
            log.warning("step %d: the rover hit the true scene after %.2f m (%.0f%% of the "
                        "path); it stopped at the last free pose", path.step, motion.length_m,
                        100 * motion.executed_fraction)
        self.state = motion.final_xy_yaw
        return ExecutionReport(path.step, motion.collided, motion.collision_samples,
                               motion.min_clearance_m, motion.length_m, motion.executed_fraction)

    def truth_surface(self) -> np.ndarray:
        """(N, 3) float32 ground-truth surface samples (evaluation and oracles only)."""
        if self._truth_surface is None:
            self._truth_surface = self.scene.surface_samples(self.cfg.eval.n_samples, seed=0)
        return self._truth_surface

    def truth_occupancy(self) -> np.ndarray:
        """(N, 3) float32 reference occupied points O*: the truth samples, one per mapper voxel."""
        from mapper.integrate import voxel_first_points
        return voxel_first_points(self.truth_surface(), self.cfg.mapper.voxel_m)

    def close(self) -> None:
        self.world.close()
