"""The simulator's logic: render what the platform senses, execute the paths it is given.

:class:`RoverSim` takes and returns plain data (no Zenoh): :meth:`render` gives the
:class:`~rovergate.types.SensorFrame` of a step, :meth:`execute` drives a
:class:`~rovergate.types.PlanPath` in the true world and reports what happened. The platform
is the rover (SE(2) on the terrain, mast camera) or the flyer (a free camera). With pose drift
the published poses are the drifted ones; rendering, collisions and ground truth use the true
pose.
"""

from __future__ import annotations

import logging

import numpy as np

from rover_sim.catalog import load_scene
from rover_sim.flyer import FlyerBody
from rover_sim.rover import RoverBody
from rover_sim.scene import Scene
from rover_sim.sensing import HAZCAM_STREAMS, Sensing
from rover_sim.world import DepthCamera, PyBulletWorld
from rovergate.config import MissionConfig
from rovergate.errors import UnknownNameError
from rovergate.geometry import (
    HAZCAMS,
    camera_from_base,
    hazcam_from_base,
    voxel_first_points,
    wrap_angle,
)
from rovergate.platforms import get_platform
from rovergate.types import ExecutionReport, PlanPath, Pose, SensorFrame

log = logging.getLogger("rovergate.sim")

#: The rover's look-around (``--rover.look-around``): the mast's pan, in degrees left, in the
#: frames after the first, second and third step in a row that the rover did not move; it
#: starts again from the first after the third.
LOOK_AROUND_DEG = (90.0, -90.0, 180.0)

#: The body of each platform (:data:`rovergate.platforms.PLATFORMS`), built for a scene and a
#: mission: its start, its state of a commanded pose, its clearance, its motion.
BODIES = {
    "rover": lambda scene, cfg: RoverBody(scene, cfg.rover),
    "flyer": lambda scene, cfg: FlyerBody(scene, cfg.flyer, cfg.rover.check_spacing_m),
}
#: Less than this far and this much turn in a step is not moving, for the look-around.
HOLD_M, HOLD_DEG = 0.01, 1.0


class RoverSim:
    """A platform in a true world: depth rendering, kinematic motion, collision reporting."""

    def __init__(self, cfg: MissionConfig, scene: Scene | None = None) -> None:
        self.cfg = cfg
        platform = get_platform(cfg.platform)
        self.scene = scene or load_scene(cfg.scene)
        if cfg.start not in self.scene.starts:
            raise UnknownNameError(f"scene {self.scene.name!r} has no start {cfg.start!r}; "
                                   f"choose one of: {', '.join(self.scene.starts)}")
        x, y, yaw = self.scene.starts[cfg.start]
        self.flying = platform.flies
        self.body: RoverBody | FlyerBody = BODIES[platform.name](self.scene, cfg)
        self.state: tuple[float, ...] = self.body.start_state(x, y, yaw)
        if self.body.clearance_at(self.state) <= 0:
            log.warning("start %r of %s touches the scene for this platform configuration",
                        cfg.start, self.scene.name)
        self.world = PyBulletWorld(self.scene, cfg.sensor, None if self.flying else cfg.rover)
        self.hazcam = (DepthCamera.of(cfg.hazcam, self.world.client)
                       if cfg.hazcam.enabled and platform.hazcams else None)
        self.sensing = Sensing(cfg.sensing, cfg.seed)
        self._drift = np.eye(4)
        self._step = 0
        self._held = 0
        """Steps in a row the rover has not moved (the look-around's place in its cycle)."""
        self._truth_surface: np.ndarray | None = None

    @property
    def T_map_base(self) -> np.ndarray:
        """The true base pose."""
        return self.body.base_pose(*self.state)

    def render(self, step: int) -> SensorFrame:
        """What the platform senses at its current pose (poses as it believes them)."""
        T_base = self.T_map_base
        T_cam = camera_from_base(T_base, self.cfg.sensor, self.cfg.platform, self.look_deg)
        self.world.set_rover_pose(T_base)
        depth = self.world.render_depth(T_cam)
        depth = self.sensing.degrade(depth, self.world.intrinsics, step)
        self._step = step
        self._drift = self.sensing.drift_transform(T_base, step)
        lever = float(np.linalg.norm(T_cam[:2, 3] - T_base[:2, 3]))  # the mast, for heading
        return SensorFrame(step, depth, self.world.intrinsics,
                           Pose.from_matrix(self._drift @ T_cam),
                           Pose.from_matrix(self._drift @ T_base),
                           self.sensing.pose_covariance(step, lever),
                           self.render_hazcams(T_base, step))

    @property
    def look_deg(self) -> float:
        """The mast's look-around pan for the next frame (0: it faces forward)."""
        if self.flying or not self.cfg.rover.look_around or not self._held:
            return 0.0
        return LOOK_AROUND_DEG[(self._held - 1) % len(LOOK_AROUND_DEG)]

    def _note_hold(self, before: tuple[float, ...]) -> None:
        """Count the steps in a row the rover has not moved (its look-around)."""
        if self.flying:
            return
        moved = (np.hypot(self.state[0] - before[0], self.state[1] - before[1]) >= HOLD_M
                 or abs(np.degrees(wrap_angle(self.state[-1] - before[-1]))) >= HOLD_DEG)
        self._held = 0 if moved else self._held + 1

    def render_hazcams(self, T_base: np.ndarray, step: int) -> dict[str, np.ndarray]:
        """The hazard cameras' depth at the true base pose, degraded as the mast's is (their
        own draws); empty without them."""
        if self.hazcam is None:
            return {}
        return {name: self.sensing.degrade(
                    self.world.render_depth(hazcam_from_base(T_base, self.cfg.hazcam, name),
                                            self.hazcam),
                    self.hazcam.intrinsics, step, HAZCAM_STREAMS[name])
                for name in HAZCAMS}

    def restore(self, step: int, path: PlanPath | None) -> None:
        """Redo step ``step`` without rendering (a restarted simulator replaying its past):
        execute the path of step - 1, then take up the frame of ``step`` as :meth:`render`
        would. Executing is deterministic, so the state after it is the one the world had."""
        if path is not None:
            self.execute(path)
        self._step = step
        self._drift = self.sensing.drift_transform(self.T_map_base, step)

    def _true_state(self, pose: Pose) -> tuple[float, ...]:
        """A commanded pose (in the platform's believed frame) as a true state."""
        p = Pose.from_matrix(np.linalg.inv(self._drift) @ pose.matrix())
        x, y, z = (float(v) for v in p.position)
        return self.body.state_of(x, y, z, p.yaw, p.pitch)

    def execute(self, path: PlanPath) -> ExecutionReport:
        """Drive along ``path``; collisions and untraversable ground stop the platform."""
        waypoints = [self._true_state(p) for p in path.poses]
        error = float(np.linalg.norm(self.sensing.drift_at(path.step + 1)[:3]))
        if not waypoints:
            clear = self.body.clearance_at(self.state)
            self._note_hold(self.state)
            return ExecutionReport(path.step, False, 0, clear, 0.0, 1.0, False, error)
        before = self.state
        motion = self.body.drive(self.state, waypoints)
        if motion.collided:
            log.warning("step %d: the %s hit the true scene after %.2f m (%.0f%% of the "
                        "path); it stopped at the last free pose", path.step, self.cfg.platform,
                        motion.length_m, 100 * motion.executed_fraction)
        elif motion.untraversable:
            log.info("step %d: untraversable ground ahead after %.2f m; the rover stopped",
                     path.step, motion.length_m)
        self.state = motion.final_xy_yaw
        self._note_hold(before)
        contact = None
        if motion.contact is not None:  # reported where the platform believes it is
            contact = tuple(float(v) for v in (self._drift @ np.r_[motion.contact, 1.0])[:3])
        return ExecutionReport(path.step, motion.collided, motion.collision_samples,
                               motion.min_clearance_m, motion.length_m, motion.executed_fraction,
                               motion.untraversable, error, contact)

    def truth_surface(self) -> np.ndarray:
        """(N, 3) float32 ground-truth surface samples (evaluation and oracles only)."""
        if self._truth_surface is None:
            self._truth_surface = self.scene.surface_samples(self.cfg.eval.n_samples, seed=0)
        return self._truth_surface

    def truth_occupancy(self) -> np.ndarray:
        """(N, 3) float32 reference occupied points O*: the truth samples, one per mapper voxel."""
        return voxel_first_points(self.truth_surface(), self.cfg.mapper.voxel_m)

    def close(self) -> None:
        self.world.close()
