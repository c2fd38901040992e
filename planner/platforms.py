"""What a planner needs to know about the platform: its states, views, checks and motions.

A :class:`MotionModel` is built for one step from the planner-facing map and the platform's
pose. The rover's states are (x, y, yaw) on the estimated ground, planned in SE(2) with its
slope and step limits; the flyer's are (x, y, z, yaw, pitch), planned in R^3 (its sphere's
position) with the view direction turned along the way. Both check collisions against the
same map the gain is rendered from.
"""

from __future__ import annotations

import abc

import numpy as np

from planner.collision import FlyerCollisionModel, OccupancyCollisionModel
from planner.motion import plan_r3, plan_se2
from rovergate.config import MissionConfig, RoverConfig
from rovergate.geometry import camera_from_base
from rovergate.types import Pose

State = tuple[float, ...]

#: The flyer may leave an invalid start within this radius (see FlyerModel.plan).
ESCAPE_RADIUS_M = 1.0


class MotionModel(abc.ABC):
    """One step's view of the platform (see the module docstring)."""

    def __init__(self, cfg: MissionConfig, points: np.ndarray, T_map_base: Pose,
                 predicted: np.ndarray | None = None) -> None:
        self.cfg = cfg
        self.points = points
        b = cfg.scene.bounds_m
        self.ground = OccupancyCollisionModel(points, cfg.rover, b, cfg.planner.ground_cell_m,
                                              cfg.planner.obstacle_voxel_m,
                                              fallback_ground_z=self._fallback_ground(T_map_base),
                                              predicted=predicted)
        self.current = self.state_of(T_map_base)

    def _fallback_ground(self, T: Pose) -> float:
        return float(T.position[2])

    @abc.abstractmethod
    def state_of(self, T_map_base: Pose) -> State: ...

    @abc.abstractmethod
    def sample(self, rng: np.random.Generator, n: int, around: State | None = None
               ) -> list[State]:
        """``n`` candidate states within one step's motion budget of ``around`` (default: the
        current state)."""

    @abc.abstractmethod
    def base_pose(self, state: State) -> Pose: ...

    def camera(self, state: State) -> np.ndarray:
        return camera_from_base(self.base_pose(state).matrix(), self.cfg.sensor,
                                self.cfg.platform)

    @abc.abstractmethod
    def is_free(self, state: State) -> bool: ...

    @abc.abstractmethod
    def plan(self, start: State, goal: State, seed: int) -> list[State] | None:
        """A collision-free motion from ``start`` to ``goal`` on the map, or None."""

    @abc.abstractmethod
    def segment_free(self, a: State, b: State) -> bool:
        """Whether the straight motion from ``a`` to ``b`` is free on the map, checked every
        ``PlannerConfig.segment_check_m`` (the look-ahead of the beam search)."""

    def _steps(self, a: State, b: State, dims: int) -> np.ndarray:
        """Fractions 0..1 along a -> b, spaced at most ``segment_check_m`` apart."""
        d = float(np.linalg.norm(np.subtract(b[:dims], a[:dims])))
        n = max(int(np.ceil(d / self.cfg.planner.segment_check_m)), 1)
        return np.linspace(0.0, 1.0, n + 1)

    @abc.abstractmethod
    def turn(self, state: State) -> State:
        """The same place, looking elsewhere (the fallback when no candidate is feasible)."""

    def is_free_turn(self, state: State) -> bool:
        """Whether turning to ``state`` from the current one is free."""
        return self.is_free(state)

    @staticmethod
    def length(states: list[State]) -> float:
        p = np.array([s[: 3 if len(s) == 5 else 2] for s in states])
        return float(np.linalg.norm(np.diff(p, axis=0), axis=1).sum()) if len(p) > 1 else 0.0


def outside_body(points: np.ndarray, T_map_base: Pose, rover: RoverConfig,
                 margin_m: float = 0.05) -> np.ndarray:
    """(N,) bool: the map points that are not inside the rover's body where it stands.

    The body occupies that space, so nothing the map holds there can be real (a robot's self
    filter); a learned prediction in the mast camera's blind band around the rover otherwise
    boxes the rover in where it stands, with no motion left that the map calls free.
    """
    if len(points) == 0:
        return np.ones(0, dtype=bool)
    p = (points - T_map_base.position) @ T_map_base.matrix()[:3, :3]  # base frame
    inside = ((np.abs(p[:, 0]) <= rover.length_m / 2 + margin_m)
              & (np.abs(p[:, 1]) <= rover.width_m / 2 + margin_m)
              & (p[:, 2] > rover.clearance_m) & (p[:, 2] < rover.body_top_m))
    return ~inside


class RoverModel(MotionModel):
    def __init__(self, cfg: MissionConfig, points: np.ndarray, T_map_base: Pose,
                 predicted: np.ndarray | None = None) -> None:
        keep = outside_body(points, T_map_base, cfg.rover)
        super().__init__(cfg, points[keep], T_map_base,
                         None if predicted is None else predicted[keep])
        if cfg.planner.known_ground_only:
            self.ground.drive_known_ground_only(*self.current[:2])

    def state_of(self, T: Pose) -> State:
        return (float(T.position[0]), float(T.position[1]), T.yaw)

    def sample(self, rng: np.random.Generator, n: int, around: State | None = None
               ) -> list[State]:
        x0, y0, _ = self.current if around is None else around
        b, pc = self.cfg.scene.bounds_m, self.cfg.planner
        r = pc.max_step_m * np.sqrt(rng.uniform(0, 1, n))
        th = rng.uniform(-np.pi, np.pi, n)
        yaw = rng.uniform(-np.pi, np.pi, n)
        margin = 0.5
        cx = np.clip(x0 + r * np.cos(th), b[0] + margin, b[3] - margin)
        cy = np.clip(y0 + r * np.sin(th), b[1] + margin, b[4] - margin)
        return list(zip(cx.tolist(), cy.tolist(), yaw.tolist(), strict=True))

    def base_pose(self, s: State) -> Pose:
        return Pose.from_xyz_yaw(s[0], s[1], self.ground.ground_z(s[0], s[1]), s[2])

    def is_free(self, s: State) -> bool:
        return self.ground.is_free(*s)

    def plan(self, start: State, goal: State, seed: int) -> list[State] | None:
        b = self.cfg.scene.bounds_m
        return plan_se2(start, goal, self.ground.is_free, (b[0], b[1], b[3], b[4]), seed=seed,
                        max_checks=self.cfg.planner.ompl_max_checks)

    def segment_free(self, a: State, b: State) -> bool:
        dyaw = (b[2] - a[2] + np.pi) % (2 * np.pi) - np.pi
        for f in self._steps(a, b, 2)[1:]:
            if not self.ground.is_free(a[0] + f * (b[0] - a[0]), a[1] + f * (b[1] - a[1]),
                                       a[2] + f * dyaw):
                return False
        return True

    def turn(self, s: State) -> State:
        return (s[0], s[1], s[2] + np.pi / 2)


class FlyerModel(MotionModel):
    def __init__(self, cfg: MissionConfig, points: np.ndarray, T_map_base: Pose,
                 predicted: np.ndarray | None = None) -> None:
        super().__init__(cfg, points, T_map_base, predicted)
        self.sphere = FlyerCollisionModel(points, cfg.flyer, self.ground)

    def _fallback_ground(self, T: Pose) -> float:
        return float(T.position[2]) - self.cfg.flyer.altitude_m

    def state_of(self, T: Pose) -> State:
        x, y, z = (float(v) for v in T.position)
        return (x, y, z, T.yaw, T.pitch)

    def sample(self, rng: np.random.Generator, n: int, around: State | None = None
               ) -> list[State]:
        x0, y0, z0 = (self.current if around is None else around)[:3]
        b, f, pc = self.cfg.scene.bounds_m, self.cfg.flyer, self.cfg.planner
        d = rng.standard_normal((n, 3))
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        r = pc.max_step_m * np.cbrt(rng.uniform(0, 1, n))
        p = np.array([x0, y0, z0]) + d * r[:, None]
        margin = 0.5
        p[:, 0] = np.clip(p[:, 0], b[0] + margin, b[3] - margin)
        p[:, 1] = np.clip(p[:, 1], b[1] + margin, b[4] - margin)
        yaw = rng.uniform(-np.pi, np.pi, n)
        pitch = np.radians(rng.uniform(f.min_pitch_deg, f.max_pitch_deg, n))
        out = []
        for (x, y, z), a, e in zip(p.tolist(), yaw.tolist(), pitch.tolist(), strict=True):
            lo, hi = self.sphere.altitude_band(x, y)
            out.append((x, y, float(np.clip(z, lo, hi)), a, e))
        return out

    def base_pose(self, s: State) -> Pose:
        return Pose.from_xyz_yaw_pitch(*s)

    def is_free(self, s: State) -> bool:
        return self.sphere.is_free(*s[:3])

    def _box(self) -> tuple[float, ...]:
        b, f = self.cfg.scene.bounds_m, self.cfg.flyer
        return (b[0], b[1], b[2] - 1.0, b[3], b[4], b[5] + f.max_altitude_m)

    def plan(self, start: State, goal: State, seed: int) -> list[State] | None:
        box = self._box()
        if not all(box[i] <= start[i] <= box[i + 3] for i in range(3)):
            return None
        # The altitude band follows a ground estimate that changes as the map grows, so the
        # flyer may find itself outside it (or a new point may land near it): near its start
        # it may move anywhere to leave such a spot; beyond, every state must be valid.
        s0 = np.array(start[:3])

        def valid(x: float, y: float, z: float) -> bool:
            near = (x - s0[0]) ** 2 + (y - s0[1]) ** 2 + (z - s0[2]) ** 2 < ESCAPE_RADIUS_M**2
            if near:
                return True
            return self.sphere.is_free(x, y, z)

        path = plan_r3(start[:3], goal[:3], valid, box, seed=seed,
                       max_checks=self.cfg.planner.ompl_max_checks)
        if path is None:
            return None
        # Turn the view from the start's to the goal's along the way, in proportion to length.
        p = np.array(path)
        run = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(p, axis=0), axis=1))]
        f = run / run[-1] if run[-1] > 0 else np.linspace(0, 1, len(p))
        dyaw = (goal[3] - start[3] + np.pi) % (2 * np.pi) - np.pi
        return [(*path[i], float(start[3] + f[i] * dyaw),
                 float(start[4] + f[i] * (goal[4] - start[4]))) for i in range(len(path))]

    def segment_free(self, a: State, b: State) -> bool:
        f = self._steps(a, b, 3)[1:, None]
        p = np.asarray(a[:3]) + f * (np.asarray(b[:3]) - np.asarray(a[:3]))
        # As in plan(): near the current state the flyer may leave a spot the map now blocks.
        check = np.sum((p - np.asarray(self.current[:3])) ** 2, axis=1) >= ESCAPE_RADIUS_M**2
        return bool(self.sphere.free_many(p[check]).all())

    def turn(self, s: State) -> State:
        return (*s[:3], s[3] + np.pi / 2, 0.0)

    def is_free_turn(self, s: State) -> bool:
        return True  # turning in place moves no part of the sphere


def motion_model(cfg: MissionConfig, points: np.ndarray, T_map_base: Pose,
                 predicted: np.ndarray | None = None) -> MotionModel:
    """The motion model of ``cfg.platform`` for one step; ``predicted`` marks the points that
    are predictions (the map's ``source``)."""
    return (FlyerModel if cfg.platform == "flyer" else RoverModel)(cfg, points, T_map_base,
                                                                   predicted)
