"""What a planner needs to know about the platform: its states, views, checks and motions.

A :class:`MotionModel` is built for one step from the planner-facing map and the platform's
pose. The rover's states are (x, y, yaw) on the estimated ground, planned in SE(2) with its
slope and step limits; the flyer's are (x, y, z, yaw, pitch), planned in R^3 (its sphere's
position) with the view direction turned along the way. Both check collisions against the
same map the gain is rendered from.

Every motion a model returns is checked on that map, whole: each state after the current one
is valid, at most ``segment_check_m`` apart (OMPL's motion check at the same resolution). The
current state itself is not judged (the platform is already there, and the map may have grown
around it). A platform whose place the map now calls blocked first escapes it (:meth:`escape`):
a straight motion of at most ``ESCAPE_M`` along which the true body (no margin) touches no map
point and moves away from the nearest one, ending in a valid state; planning starts there. A
flyer that the map leaves free but that is outside its altitude band (the ground estimated
under it moved) returns towards the band vertically, by at most one step's motion budget, each
state of the way free with the margin and in known free space.
With no escape it turns in place if the turn is free, or stays. The platform never leaves the scored
region: its states keep its whole body (its reach) inside the footprint of the box of
interest, the region of every map it is given (:func:`rovergate.geometry.in_region`).
"""

from __future__ import annotations

import abc
import math

import numpy as np

from planner.collision import (
    BODY_MARGIN_M,
    GRID_MARGIN_M,
    FlyerCollisionModel,
    OccupancyCollisionModel,
)
from planner.freespace import FreeSpace
from planner.motion import plan_r3, plan_se2
from planner.traversability import BELLY, TerrainMap
from rovergate.config import LOCAL_INSET_M, MissionConfig, RoverConfig
from rovergate.geometry import camera_from_base
from rovergate.types import Pose

State = tuple[float, ...]

#: Turns are checked every this many radians (as the simulator executes them).
TURN_CHECK_RAD = np.radians(5.0)
#: The farthest a platform moves to leave a spot the map now blocks (see MotionModel.escape).
ESCAPE_M = 0.6
#: Spacing of the escape's checks.
ESCAPE_STEP_M = 0.05
#: The rover's escape turns in place by these angles (degrees) before it drives, first to last.
ESCAPE_TURNS_DEG = (0, 20, -20, 45, -45, 90, -90)
#: The rover's turns in place when no candidate is feasible (degrees), first to last.
FALLBACK_TURNS_DEG = (90, -90, 45, -45, 20, -20)
#: The rover with a traversability layer draws this many times the candidates it needs and
#: keeps those on ground it can drive (RoverModel.sample).
SAMPLE_OVERDRAW = 4
#: How far inside the altitude band a flyer that left it returns (the band's edges move with
#: the ground the map estimates, by a few centimetres a step).
BAND_INSET_M = 0.1
#: How far inside the planner's local window the collision model's grid ends: its own 5 m
#: margin and the snap of its corner to the ground cells (under a cell) stay within the
#: window's points. The states it may plan through stay LOCAL_INSET_M inside.
LOCAL_GRID_INSET_M = GRID_MARGIN_M + 1.0


class MotionModel(abc.ABC):
    """One step's view of the platform (see the module docstring)."""

    def __init__(self, cfg: MissionConfig, points: np.ndarray, T_map_base: Pose,
                 predicted: np.ndarray | None = None, contacts: np.ndarray | None = None,
                 ground_ref=None) -> None:
        self.cfg = cfg
        self.points = points
        self.contacts = np.zeros((0, 3)) if contacts is None else np.asarray(contacts)
        self._centre = (float(T_map_base.position[0]), float(T_map_base.position[1]))
        b = local_bounds(cfg, *self._centre)
        self.ground = OccupancyCollisionModel(points, cfg.rover, b, cfg.planner.ground_cell_m,
                                              cfg.planner.obstacle_voxel_m,
                                              fallback_ground_z=self._fallback_ground(T_map_base),
                                              predicted=predicted, contacts=self.contacts,
                                              ground_ref=ground_ref)
        self.current = self.state_of(T_map_base)
        self.prefix: list[State] = []
        """The escape from a blocked start: states before :attr:`current` in every motion."""

    def leave_blocked_start(self) -> None:
        """If the map blocks the current state, escape it (module docstring): the motion's
        prefix becomes [the blocked state] and planning starts where the escape ends."""
        if self.is_free(self.current):
            return
        way = self.escape_way()
        if way:
            self.prefix = [self.current, *way[:-1]]
            self.current = way[-1]

    def admit(self, states: list[State]) -> str | None:
        """The hazard the platform's traversability layer finds along the motion through
        ``states`` (the rover's ACE, :mod:`planner.traversability`), or None: the motion may
        be driven. The flyer has no such layer."""
        return None

    def refuse(self, state: State) -> None:
        """Count why the traversability layer refuses a candidate the planner drops (the
        rover's :meth:`planner.traversability.TerrainMap.why_not`; nothing on the flyer)."""
        return None

    def stale(self, states: list[State]) -> np.ndarray:
        """(N,) bool: candidate states the planner should try last, as the platform dithered
        there lately (the rover's :meth:`planner.traversability.TerrainMap.dither_spots`;
        none on the flyer)."""
        return np.zeros(len(states), dtype=bool)

    def avoid(self, states: list[State]) -> np.ndarray:
        """(N,) int: the tier each candidate state is tried in, after the best of the lower
        tiers: 2 near where the platform dithered lately (:meth:`stale`), 1 where the rover
        stood at one of the last ``TraverseConfig.revisit_steps`` steps, else 0."""
        return 2 * self.stale(states).astype(np.int64) + self.revisit(states)

    def revisit(self, states: list[State]) -> np.ndarray:
        """(N,) int: 1 for candidate states near where the platform stood lately (the
        rover's; none on the flyer), else 0."""
        return np.zeros(len(states), dtype=np.int64)

    def away(self, states: list[State]) -> np.ndarray:
        """(N,) float: each candidate state's distance in the plane from the nearest place
        the platform stood at a step boundary (the rover's, from its traversability layer;
        zeros on the flyer): how far a move there takes it from where it has been."""
        return np.zeros(len(states))

    def backout(self, start: State) -> list[State]:
        """The rover's way back along where it came from (checked by its traversability
        layer only), from ``start``; empty where there is none (and on the flyer)."""
        return []

    def escape_way(self) -> list[State]:
        """The states an escape passes through from the blocked current one, ending in a
        valid state; empty if there is none. By default a straight one (:meth:`escape`)."""
        end = self.escape()
        return [] if end is None else [end]

    def escape(self) -> State | None:
        """A valid state a checked straight escape reaches from the blocked current one."""
        return None

    @property
    @abc.abstractmethod
    def reach_m(self) -> float:
        """How far the platform's body reaches from its state's position (in x, y)."""

    def inner_box(self) -> tuple[float, float, float, float]:
        """(xmin, ymin, xmax, ymax) of the positions whose body stays in the scored region,
        widened to hold the current position (a start nearer the edge can still leave)."""
        b, r = self.cfg.scene.bounds_m, self.reach_m + 0.1
        x, y = self.current[0], self.current[1]
        box = (min(b[0] + r, x), min(b[1] + r, y), max(b[3] - r, x), max(b[4] - r, y))
        # ...and cut to the planner's local window, where this step's map is whole.
        w = self.cfg.planner.local_half_m - LOCAL_INSET_M
        cx, cy = self._centre
        return (max(box[0], min(cx - w, x)), max(box[1], min(cy - w, y)),
                min(box[2], max(cx + w, x)), min(box[3], max(cy + w, y)))

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

    def turns(self, state: State) -> list[State]:
        """The turns in place a platform with no feasible candidate tries, first to last."""
        return [self.turn(state)]

    def is_free_turn(self, state: State) -> bool:
        """Whether turning in place from the current state to ``state`` is free, checked every
        ``TURN_CHECK_RAD`` of the turn (the current state is not judged)."""
        a = self.current[2] if len(state) == 3 else self.current[3]
        b = state[2] if len(state) == 3 else state[3]
        d = (b - a + np.pi) % (2 * np.pi) - np.pi
        n = max(int(np.ceil(abs(d) / TURN_CHECK_RAD)), 1)
        for f in np.linspace(0.0, 1.0, n + 1)[1:]:
            s = list(state)
            s[2 if len(state) == 3 else 3] = a + f * d
            if not self.is_free(tuple(s)):
                return False
        return True

    @staticmethod
    def length(states: list[State]) -> float:
        p = np.array([s[: 3 if len(s) == 5 else 2] for s in states])
        return float(np.linalg.norm(np.diff(p, axis=0), axis=1).sum()) if len(p) > 1 else 0.0


def local_bounds(cfg: MissionConfig, x: float, y: float) -> tuple[float, ...]:
    """The scene's box of interest cut to the part of the planner's local window around
    (x, y) that the collision model's grid covers: ``LOCAL_GRID_INSET_M`` inside the window,
    so that the grid's own margin stays within the window's points, and its low corner on
    the lattice of the whole box's ground cells (the same cells wherever the window stands).
    A box that fits in the window is returned as it is."""
    b, cell = cfg.scene.bounds_m, cfg.planner.ground_cell_m
    w = cfg.planner.local_half_m - LOCAL_GRID_INSET_M
    lo = [b[0], b[1]]
    for i, c in enumerate((x, y)):
        if c - w > b[i]:
            lo[i] = b[i] + math.floor((c - w - b[i]) / cell) * cell
    hi = [b[3] if x + w >= b[3] else x + w, b[4] if y + w >= b[4] else y + w]
    return (lo[0], lo[1], b[2], max(hi[0], lo[0]), max(hi[1], lo[1]), b[5])


def flyer_altitudes(cfg: MissionConfig) -> tuple[float, float]:
    """The heights the flyer may plan through: from 1 m below the scene's bounds to its
    highest altitude above them (its states, and the free space the planner keeps)."""
    b = cfg.scene.bounds_m
    return b[2] - 1.0, b[5] + cfg.flyer.max_altitude_m


def _inside(state, box: tuple[float, float, float, float]) -> bool:
    return box[0] <= state[0] <= box[2] and box[1] <= state[1] <= box[3]


def outside_body(points: np.ndarray, T_map_base: Pose, rover: RoverConfig,
                 margin_m: float = 0.05) -> np.ndarray:
    """(N,) bool: the map points that are not inside the rover's body where it stands.

    The body occupies that space, so nothing the map holds there can be real (a robot's self
    filter); a learned prediction in the mast camera's blind band around the rover otherwise
    boxes the rover in where it stands, with no motion left that the map calls free. The
    space is the body as the collision model checks it, its height band widened by
    ``BODY_MARGIN_M`` below and above (:mod:`planner.collision`): a point under the belly in
    that band would block the rover where it already stands, and anything real there is
    lower than its true clearance, so it passes under the body wherever the body goes
    (the traversability layer's ACE judges the ground under the belly from measured
    returns).
    """
    if len(points) == 0:
        return np.ones(0, dtype=bool)
    p = (points - T_map_base.position) @ T_map_base.matrix()[:3, :3]  # base frame
    inside = ((np.abs(p[:, 0]) <= rover.length_m / 2 + margin_m)
              & (np.abs(p[:, 1]) <= rover.width_m / 2 + margin_m)
              & (p[:, 2] > rover.clearance_m - BODY_MARGIN_M)
              & (p[:, 2] < rover.body_top_m + BODY_MARGIN_M))
    return ~inside


class RoverModel(MotionModel):
    """The rover: a state is free when the body is clear on the planner-facing map (its
    collision channel, predictions included: they may block) and, with a traversability
    layer (``terrain``), on ground the rover has observed or stood on, clear of what it
    measured (:meth:`planner.traversability.TerrainMap.free`); every motion it is sent on
    passes that layer's ACE (:meth:`admit`)."""

    def __init__(self, cfg: MissionConfig, points: np.ndarray, T_map_base: Pose,
                 predicted: np.ndarray | None = None, free: FreeSpace | None = None,
                 contacts: np.ndarray | None = None, terrain: TerrainMap | None = None
                 ) -> None:
        # The self filter is for map points; a contact is where the bumper touched the scene,
        # on the body's own surface when the touch was where the rover now stands: it stays,
        # and the rover escapes it (escape_way) instead of driving into it again.
        keep = outside_body(points, T_map_base, cfg.rover)
        super().__init__(cfg, points[keep], T_map_base,
                         None if predicted is None else predicted[keep], contacts,
                         ground_ref=None if terrain is None else terrain.ground_at)
        self.terrain = terrain

    @property
    def reach_m(self) -> float:
        return float(np.hypot(self.cfg.rover.length_m, self.cfg.rover.width_m)) / 2

    def state_of(self, T: Pose) -> State:
        return (float(T.position[0]), float(T.position[1]), T.yaw)

    def sample(self, rng: np.random.Generator, n: int, around: State | None = None
               ) -> list[State]:
        """With a traversability layer, ``SAMPLE_OVERDRAW`` times ``n`` states are drawn and
        the first ``n`` the layer's search-time check allows are kept (then the others, in
        the order drawn, to make up ``n``): most of a disc around the rover is ground it has
        not seen, and a candidate there can never be driven to."""
        x0, y0, _ = self.current if around is None else around
        pc = self.cfg.planner
        m = n * (SAMPLE_OVERDRAW if self.terrain is not None else 1)
        r = pc.max_step_m * np.sqrt(rng.uniform(0, 1, m))
        th = rng.uniform(-np.pi, np.pi, m)
        yaw = rng.uniform(-np.pi, np.pi, m)
        box = self.inner_box()
        cx = np.clip(x0 + r * np.cos(th), box[0], box[2])
        cy = np.clip(y0 + r * np.sin(th), box[1], box[3])
        states = list(zip(cx.tolist(), cy.tolist(), yaw.tolist(), strict=True))
        if self.terrain is None:
            return states
        ok = [self.terrain.free(*s) for s in states]
        return ([s for s, f in zip(states, ok, strict=True) if f]
                + [s for s, f in zip(states, ok, strict=True) if not f])[:n]

    def base_pose(self, s: State) -> Pose:
        return Pose.from_xyz_yaw(s[0], s[1], self.ground.ground_z(s[0], s[1]), s[2])

    def is_free(self, s: State) -> bool:
        return ((self.terrain is None or self.terrain.free(*s[:3]))
                and self.ground.is_free(*s[:3]))

    def _free_xyyaw(self, x: float, y: float, yaw: float) -> bool:
        return self.is_free((x, y, yaw))

    def admit(self, states: list[State]) -> str | None:
        return None if self.terrain is None else self.terrain.admit(states)

    def refuse(self, state: State) -> None:
        if self.terrain is not None:
            self.terrain.why_not(*state[:3])

    def stale(self, states: list[State]) -> np.ndarray:
        spots = np.zeros((0, 2)) if self.terrain is None else self.terrain.dither_spots()
        if not len(spots) or not len(states):
            return np.zeros(len(states), dtype=bool)
        xy = np.array([s[:2] for s in states], dtype=np.float64)
        d = np.linalg.norm(xy[:, None, :] - spots[None], axis=2).min(axis=1)
        return d < self.cfg.traverse.dither_radius_m

    def away(self, states: list[State]) -> np.ndarray:
        if self.terrain is None or not self.terrain.visited or not len(states):
            return np.zeros(len(states))
        spots = np.asarray(self.terrain.visited, dtype=np.float64).reshape(-1, 2)
        xy = np.array([s[:2] for s in states], dtype=np.float64)
        return np.sqrt(((xy[:, None, :] - spots[None]) ** 2).sum(axis=2).min(axis=1))

    def revisit(self, states: list[State]) -> np.ndarray:
        t = self.cfg.traverse
        out = np.zeros(len(states), dtype=np.int64)
        if self.terrain is None or not t.revisit_steps or not len(states):
            return out
        spots = np.asarray(self.terrain.visited[-1 - t.revisit_steps:-1],
                           dtype=np.float64).reshape(-1, 2)
        if not len(spots):
            return out
        xy = np.array([s[:2] for s in states], dtype=np.float64)
        d = np.linalg.norm(xy[:, None, :] - spots[None], axis=2).min(axis=1)
        out[d < t.revisit_m] = 1
        return out

    def backout(self, start: State) -> list[State]:
        if self.terrain is None:
            return []
        box = self.inner_box()
        return self.terrain.backout(start, self.cfg.planner.max_step_m,
                                    self.cfg.traverse.backout_steps,
                                    extra_ok=lambda s: _inside(s, box))

    def plan(self, start: State, goal: State, seed: int) -> list[State] | None:
        return plan_se2(start, goal, self._free_xyyaw, self.inner_box(), seed=seed,
                        max_checks=self.cfg.planner.ompl_max_checks)

    def segment_free(self, a: State, b: State) -> bool:
        dyaw = (b[2] - a[2] + np.pi) % (2 * np.pi) - np.pi
        for f in self._steps(a, b, 2)[1:]:
            if not self.is_free((a[0] + f * (b[0] - a[0]), a[1] + f * (b[1] - a[1]),
                                 a[2] + f * dyaw)):
                return False
        return True

    def turn(self, s: State) -> State:
        return (s[0], s[1], s[2] + np.pi / 2)

    def turns(self, s: State) -> list[State]:
        """Quarter turns either way, then smaller ones (``FALLBACK_TURNS_DEG``): beside the
        body is ground no camera has seen, and a smaller turn sweeps less of it, while each
        turn shows the hazard cameras more of it for the next step."""
        return [(s[0], s[1], s[2] + np.radians(a)) for a in FALLBACK_TURNS_DEG]

    def escape_way(self) -> list[State]:
        """The shortest of: a turn in place of at most 90 degrees (or none), then a straight
        move of at most ``ESCAPE_M`` in one of eight directions of the body (ahead, behind,
        sideways, diagonal: the rover moves in SE(2) as its planner plans it, OMPL's
        straight interpolation of x, y and heading), ending in a valid state. Every state of
        the way, checked every ``TURN_CHECK_RAD`` and ``ESCAPE_STEP_M``, is on traversable
        ground in the scored region with the true body, narrowed by the map's error
        (``ESCAPE_SHRINK_M``), off the map's obstacles: a rover the bumper stopped against a
        rock stands closer to the rock's samples than the planner's margin, often closer than
        its true body, and a rock along its side blocks it ahead and behind and swings into
        either end when it turns in place. The narrowing is for the map's error only: where
        the bumper touched the scene (a contact, exact) the way never comes nearer than where
        it starts. Length: the move plus the turn's sweep at the body's corner."""
        x, y, yaw = self.current
        box = self.inner_box()
        near = self.contacts[np.hypot(self.contacts[:, 0] - x, self.contacts[:, 1] - y)
                             < ESCAPE_M + self.reach_m + 0.5, :2] if len(self.contacts) else None
        start_gap = self._contact_gap(self.current, near)

        def free(s: State) -> bool:
            # The narrowed body allows for the map's error, not for a contact's: a contact
            # is exact, and the way may not come nearer to one than where it starts.
            return (_inside(s, box) and self.ground.is_free(*s, margin="escape")
                    and self._contact_gap(s, near) >= start_gap - 1e-9
                    and (self.terrain is None or self.terrain.assess(*s) in (None, BELLY)))
        best: tuple[float, list[State]] | None = None
        for turn in np.radians(ESCAPE_TURNS_DEG):
            n = max(int(np.ceil(abs(turn) / TURN_CHECK_RAD)), 1)
            if turn and not all(free((x, y, yaw + f * turn))
                                for f in np.linspace(0.0, 1.0, n + 1)[1:]):
                continue
            swept = abs(turn) * self.reach_m
            heading = yaw + turn
            turned = [(x, y, heading)] if turn else []
            if turn and self.is_free(turned[0]):
                if best is None or swept < best[0]:
                    best = (swept, turned)
                continue
            for direction in np.radians(np.arange(0, 360, 45)):
                ux, uy = np.cos(heading + direction), np.sin(heading + direction)
                for d in np.arange(ESCAPE_STEP_M, ESCAPE_M + 1e-9, ESCAPE_STEP_M):
                    if best is not None and swept + d >= best[0]:
                        break
                    s = (x + d * ux, y + d * uy, heading)
                    if not free(s):
                        break
                    if self.is_free(s):
                        best = (swept + d, [*turned, s])
                        break
        return [] if best is None else best[1]

    def _contact_gap(self, s: State, contacts: np.ndarray | None) -> float:
        """The smallest distance in the plane from ``contacts`` (K, 2) to the true body's
        footprint at ``s`` (0 for one inside it; inf without contacts)."""
        if contacts is None or not len(contacts):
            return np.inf
        c, sn = np.cos(s[2]), np.sin(s[2])
        d = contacts - np.array(s[:2])
        bx, by = d[:, 0] * c + d[:, 1] * sn, -d[:, 0] * sn + d[:, 1] * c
        ex = np.maximum(np.abs(bx) - self.cfg.rover.length_m / 2, 0.0)
        ey = np.maximum(np.abs(by) - self.cfg.rover.width_m / 2, 0.0)
        return float(np.hypot(ex, ey).min())


class FlyerModel(MotionModel):
    def __init__(self, cfg: MissionConfig, points: np.ndarray, T_map_base: Pose,
                 predicted: np.ndarray | None = None, free: FreeSpace | None = None,
                 contacts: np.ndarray | None = None, terrain: TerrainMap | None = None
                 ) -> None:
        # (A flyer reads no terrain layer.) Self filter: nothing the map holds inside the sphere
        # where the flyer is can be real (the camera cannot see within its minimum range; a
        # prediction can land there).
        keep = (np.sum((points - T_map_base.position) ** 2, axis=1)
                > cfg.flyer.radius_m ** 2) if len(points) else np.ones(0, dtype=bool)
        points = points[keep]
        super().__init__(cfg, points, T_map_base, None if predicted is None else predicted[keep])
        solid = points if contacts is None or not len(contacts) else np.vstack(
            [points, contacts]).astype(np.float32)
        self.sphere = FlyerCollisionModel(solid, cfg.flyer, self.ground,
                                          margin_m=cfg.planner.flyer_margin_m, free=free)

    def _fallback_ground(self, T: Pose) -> float:
        return float(T.position[2]) - self.cfg.flyer.altitude_m

    @property
    def reach_m(self) -> float:
        return self.sphere.reach

    def state_of(self, T: Pose) -> State:
        x, y, z = (float(v) for v in T.position)
        return (x, y, z, T.yaw, T.pitch)

    def sample(self, rng: np.random.Generator, n: int, around: State | None = None
               ) -> list[State]:
        x0, y0, z0 = (self.current if around is None else around)[:3]
        f, pc = self.cfg.flyer, self.cfg.planner
        d = rng.standard_normal((n, 3))
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        r = pc.max_step_m * np.cbrt(rng.uniform(0, 1, n))
        p = np.array([x0, y0, z0]) + d * r[:, None]
        box = self.inner_box()
        p[:, 0] = np.clip(p[:, 0], box[0], box[2])
        p[:, 1] = np.clip(p[:, 1], box[1], box[3])
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
        lo, hi = flyer_altitudes(self.cfg)
        x0, y0, x1, y1 = self.inner_box()
        return (x0, y0, min(lo, self.current[2]), x1, y1, max(hi, self.current[2]))

    def plan(self, start: State, goal: State, seed: int) -> list[State] | None:
        box = self._box()
        if not all(box[i] <= start[i] <= box[i + 3] for i in range(3)):
            return None
        path = plan_r3(start[:3], goal[:3], self.sphere.is_free, box, seed=seed,
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
        return bool(self.sphere.free_many(p).all())

    def turn(self, s: State) -> State:
        return (*s[:3], s[3] + np.pi / 2, 0.0)

    def escape(self) -> State | None:
        """Back into the altitude band, or away from the nearest map point.

        A state the map leaves free but that lies outside the altitude band (the ground under
        it, as the map now estimates it, moved: a prediction filled a crater floor below a
        flyer that was in the band when it got there) returns towards the band vertically
        (:meth:`_back_into_band`): every state of the way is free of the map with the margin
        and in known free space; the way is at most one step's motion budget, so a drop deeper
        than that takes several steps (the end is then still outside the band, and the step
        is spent on the way there). Otherwise, or if that way is blocked: away from the
        nearest map point, or up or down, at most ``ESCAPE_M``: every state of the way keeps
        the true sphere (no margin) off the map, comes no nearer to the map than the escape's
        start is and stays in known free space; the end is valid."""
        p0 = np.asarray(self.current[:3], dtype=np.float64)
        if self.sphere.is_free(*p0, band=False):
            end = self._back_into_band(p0)
            if end is not None:
                return end
        directions = []
        near = self.sphere.nearest(p0)
        if near is not None and np.linalg.norm(p0 - near) > 1e-6:
            directions.append((p0 - near) / np.linalg.norm(p0 - near))
        directions += [np.array([0.0, 0.0, 1.0]), np.array([0.0, 0.0, -1.0])]
        box = self.inner_box()
        start = self.sphere.distance(p0)
        for u in directions:
            for d in np.arange(ESCAPE_STEP_M, ESCAPE_M + 1e-9, ESCAPE_STEP_M):
                p = p0 + d * u
                dist = self.sphere.distance(p)
                # Never nearer to the map than where the escape starts (it may come nearer
                # between two checks than at the one before, as a way round a corner does).
                if (not _inside(p, box) or dist < start - 1e-9 or dist <= self.cfg.flyer.radius_m
                        or (self.sphere.free is not None
                            and not self.sphere.free.is_free(*p))):
                    break
                s = (*(float(v) for v in p), *self.current[3:])
                if self.is_free(s):
                    return s
        return None

    def _back_into_band(self, p0: np.ndarray) -> State | None:
        """Vertically towards ``BAND_INSET_M`` inside the band's nearer edge (its middle if the
        band is thinner), at most one step's motion budget: a deeper drop is made up over
        several steps. None if a state of the way is not free of the map (with the margin,
        band aside) or not in known free space."""
        lo, hi = self.sphere.altitude_band(p0[0], p0[1])
        if hi - lo < 2 * BAND_INSET_M:
            target = (lo + hi) / 2
        else:
            target = min(max(p0[2], lo + BAND_INSET_M), hi - BAND_INSET_M)
        budget = self.cfg.planner.max_step_m
        target = p0[2] + float(np.clip(target - p0[2], -budget, budget))
        n = max(int(np.ceil(abs(target - p0[2]) / ESCAPE_STEP_M)), 1)
        way = np.repeat(p0[None], n, axis=0)
        way[:, 2] = np.linspace(p0[2], target, n + 1)[1:]
        if not self.sphere.free_many(way, band=False).all():
            return None
        return (*(float(v) for v in way[-1]), *self.current[3:])

    def is_free_turn(self, s: State) -> bool:
        return True  # turning in place moves no part of the sphere (nor leaves the place)


#: The motion model of each platform (:data:`rovergate.platforms.PLATFORMS`).
MOTION_MODELS: dict[str, type[MotionModel]] = {"rover": RoverModel, "flyer": FlyerModel}


def motion_model(cfg: MissionConfig, points: np.ndarray, T_map_base: Pose,
                 predicted: np.ndarray | None = None, free: FreeSpace | None = None,
                 contacts: np.ndarray | None = None, terrain: TerrainMap | None = None
                 ) -> MotionModel:
    """The motion model of ``cfg.platform`` for one step; ``predicted`` marks the points that
    are predictions (the map's ``source``); ``free`` is the known free space (the flyer keeps
    to it); ``contacts`` are where the platform touched the scene (obstacles from then on);
    ``terrain`` is the rover's traversability layer (prepared for this step)."""
    return MOTION_MODELS[cfg.platform](cfg, points, T_map_base, predicted, free, contacts,
                                       terrain)
