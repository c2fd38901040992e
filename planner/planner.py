"""Planners: choose where to look next and how to get there.

The contract of a planner (:class:`Planner`): given the step, the planner-facing occupancy of
that step and the rover's base pose, return a :class:`~rovergate.types.PlanPath` of rover base
poses whose first pose is the current one. The same map must serve both gain and collision
checking. A planner must be deterministic for a given seed and step.
"""

from __future__ import annotations

import abc
import importlib.metadata
import logging
from dataclasses import dataclass

import numpy as np

from planner.freespace import FreeSpace
from planner.gain import GainField
from planner.platforms import MotionModel, motion_model
from planner.traversability import TerrainMap
from rovergate.config import MissionConfig
from rovergate.errors import UnknownNameError
from rovergate.geometry import camera_from_base
from rovergate.types import (
    CameraIntrinsics,
    Channel,
    PlannerMap,
    PlanPath,
    Pose,
    Source,
    xyz,
)

log = logging.getLogger("rovergate.planner")


@dataclass
class PlanResult:
    """A chosen path and why."""

    path: PlanPath
    gain: int
    """Novel points the chosen view is expected to see."""
    attempts: int
    """Candidates sent to OMPL before one was feasible."""
    reason: str
    """'best-feasible', 'rotate' (nothing feasible: turn in place), 'escape' (only the way out
    of a spot the map now blocks), 'backout' (the rover backs along the way it came) or
    'stay'."""
    rejected: PlanPath
    """Goal poses of the candidates tried and found infeasible, in the order tried."""


#: What a planner rendered in a step: the map it was given, the gain field it built, and the
#: indices in that map's points of the field's points (those near the vehicle that serve
#: the gain).
Rendered = tuple[PlannerMap, GainField, np.ndarray]


class Planner(abc.ABC):
    """Base class of planners; see the module docstring for the contract."""

    def __init__(self, cfg: MissionConfig) -> None:
        self.cfg = cfg
        self.rendered: Rendered | None = None
        """The map, the gain field and the indices in the map of the field's points, of the
        latest step (:func:`counted_points` reads it)."""

    @abc.abstractmethod
    def plan(self, step: int, occupancy: PlannerMap, T_map_base: Pose,
             free: FreeSpace | None = None, contacts: np.ndarray | None = None,
             terrain: TerrainMap | None = None) -> PlanResult:
        """The motion for step ``step`` (``free``: the known free space, which the flyer
        keeps to; ``contacts``: (K, 3) points where the platform touched the scene, obstacles
        to its collision checks though not part of the map's gain; ``terrain``: the rover's
        traversability layer, prepared for this step, which every motion must pass)."""

    def _setup(self, step: int, occupancy: PlannerMap, T_map_base: Pose,
               free: FreeSpace | None = None, contacts: np.ndarray | None = None,
               terrain: TerrainMap | None = None
               ) -> tuple[MotionModel, np.random.Generator, GainField]:
        """One step's motion model, random generator (seeded by seed and step) and gain field,
        all read from the same planner-facing map."""
        cfg, pc = self.cfg, self.cfg.planner
        # The map near the vehicle only (--planner.local-half-m): what a step's views and
        # motions can reach, so that the step's cost does not grow with a long traverse's map.
        local, kept = occupancy.within(float(T_map_base.position[0]),
                                       float(T_map_base.position[1]), pc.local_half_m)
        # Each use of the map sees the points that serve it (gated-split keeps apart what
        # attracts and what blocks; every other condition gives both all of its points).
        blocking = local.serving(Channel.COLLISION)
        gain_at = np.flatnonzero((local.points["channels"] & Channel.GAIN) != 0)
        attracting = PlannerMap(local.step, local.points[gain_at], local.suppressed)
        model = motion_model(cfg, xyz(blocking.points), T_map_base,
                             predicted=blocking.points["source"] == Source.PREDICTED, free=free,
                             contacts=contacts, terrain=terrain)
        model.leave_blocked_start()
        rng = np.random.default_rng([cfg.seed, step])
        field = gain_field(cfg, xyz(attracting.points),
                           novel_mask(attracting, pc.observed_min_views))
        self.rendered = (occupancy, field, gain_at if kept is None else kept[gain_at])
        return model, rng, field


def counted_points(cfg: MissionConfig, occupancy: PlannerMap, goal: Pose,
                   rendered: Rendered | None = None) -> np.ndarray:
    """(K,) uint32 indices into ``occupancy.points`` of the points the gain of the view from
    ``goal`` (a base pose) counts: the novel points, among those serving the gain, of the
    primitives that view sees. ``rendered``: the map, gain field and field points' indices
    the planner built this step (:meth:`Planner._setup`), read when it is of this map; else
    the field is built from every point serving the gain."""
    if rendered is not None and rendered[0] is occupancy:
        field, serving = rendered[1], rendered[2]
    else:
        serving = np.flatnonzero((occupancy.points["channels"] & Channel.GAIN) != 0)
        attracting = occupancy.serving(Channel.GAIN)
        field = gain_field(cfg, xyz(attracting.points),
                           novel_mask(attracting, cfg.planner.observed_min_views))
    cam = camera_from_base(goal.matrix(), cfg.sensor, cfg.platform)
    return serving[field.counted(field.visible(cam))].astype(np.uint32)


def gain_field(cfg: MissionConfig, points: np.ndarray, novel: np.ndarray) -> GainField:
    """The gain field the planner renders: ``novel`` (N,) bool weights ``points``."""
    pc, sensor = cfg.planner, cfg.sensor
    k = CameraIntrinsics.from_fov(sensor.width_px, sensor.height_px,
                                  sensor.vfov_deg).scaled(pc.gain_resolution)
    return GainField(points, novel, pc.gain_voxel_m, k, sensor.min_range_m, sensor.max_range_m,
                     pc.zbuffer_tolerance_m)


def novel_mask(occupancy: PlannerMap, observed_min_views: int) -> np.ndarray:
    """(N,) bool: map points not yet seen in ``observed_min_views`` frames.

    One rule for every point, whatever its source (observed, predicted, reference): its
    ``views`` are the frames whose camera saw the place where it lies (the gate counts them,
    :mod:`gate.views`). A point glimpsed once, far away or at a grazing angle, is worth
    another look.
    """
    return occupancy.points["views"] < observed_min_views


def plan_seed(cfg: MissionConfig, step: int, tried: int) -> int:
    """OMPL's seed for the motion to the candidate tried after ``tried`` others."""
    return cfg.seed * 100_003 + step * 101 + tried + 1


def fallback(step: int, model: MotionModel, T_map_base: Pose, rejected: list) -> PlanResult:
    """No candidate was feasible: turn in place where the turn is free (a quarter turn, left
    first; the rover also right, then smaller turns), else leave the spot the map blocks,
    else back out along the way the rover came (:meth:`MotionModel.backout`: checked by its
    traversability layer alone, as it stood at every pose of it), else stay (the simulator's
    rover then pans its mast to look around, :data:`rover_sim.sim.LOOK_AROUND_DEG`). Where the
    rover has dithered lately (:meth:`MotionModel.stale`), it backs out first of all. Every
    motion passes the layer's ACE."""
    tried = GreedyPlanner._to_path(step, rejected, model)
    start = model.state_of(T_map_base)

    def backout(way: list) -> PlanResult:
        return PlanResult(GreedyPlanner._to_path(step, [start, *way], model), 0, len(rejected),
                          "backout", tried)
    # Turning in place where the rover has dithered lately has shown it nothing it can
    # drive to: back out first.
    way = model.backout(start) if model.stale([start])[0] else None
    if way:
        return backout(way)
    for turn in model.turns(model.current):
        if model.is_free_turn(turn) and model.admit(model.prefix + [model.current, turn]) is None:
            return PlanResult(motion(step, [model.current, turn], model), 0, len(rejected),
                              "rotate", tried)
    if model.prefix and model.admit(model.prefix + [model.current]) is None:
        return PlanResult(motion(step, [model.current], model), 0, len(rejected), "escape",
                          tried)
    if way is None:  # (not tried above)
        way = model.backout(start)
    if way:
        return backout(way)
    return PlanResult(PlanPath(step, [T_map_base]), 0, len(rejected), "stay", tried)


def motion(step: int, states: list, model: MotionModel) -> PlanPath:
    """The path to execute: the escape from a blocked spot, if any, then ``states``."""
    return GreedyPlanner._to_path(step, model.prefix + states, model)


def best_feasible(cfg: MissionConfig, step: int, model: MotionModel, field: GainField,
                  candidates: list, rejected: list, seed_base: int = 0,
                  refuse: bool = True) -> PlanResult | None:
    """The greedy choice: ``candidates`` scored by their own view's rendered gain, tried best
    first (then the nearer; where the rover dithered lately, last) with OMPL until one is
    feasible within the motion budget and passes the layer's ACE; None if none does. Tried
    goals that fail are appended to ``rejected``. At most ``max_attempts`` are tried, every
    one where the rover dithered lately (its best candidates failed there before)."""
    pc = cfg.planner
    if not candidates:
        return None
    gains = np.array([field.gain(field.visible(model.camera(c))) for c in candidates],
                     dtype=np.int64)
    here = np.array(model.current[:cfg.vehicle.dims])
    travel = np.array([np.linalg.norm(np.array(c[:len(here)]) - here) for c in candidates])
    if gains.max() < pc.explore_below:
        # Nothing left to see within reach (a long traverse's seen ground): away from every
        # place the platform stood instead, the farthest first, towards ground not yet seen.
        order = np.lexsort((-model.away(candidates), model.avoid(candidates)))
    else:
        order = np.lexsort((travel, -gains, model.avoid(candidates)))
    attempts = len(order) if model.stale([model.current])[0] else pc.max_attempts
    for k, i in enumerate(order[:attempts]):
        goal = candidates[i]
        if refuse:
            model.refuse(goal)
        if model.is_free(goal):
            seed = plan_seed(cfg, step, len(rejected) if not seed_base else seed_base + k)
            path = model.plan(model.current, goal, seed=seed)
            if (path is not None and model.length(model.prefix + path) <= pc.max_step_m
                    and model.admit(model.prefix + path) is None):
                return PlanResult(motion(step, path, model), int(gains[i]), len(rejected) + 1,
                                  "best-feasible", GreedyPlanner._to_path(step, rejected, model))
        rejected.append(goal)
    return None


class GreedyPlanner(Planner):
    """Next best view within the motion budget, as the paper's fixed planner does per step.

    Sample candidate states within ``max_step_m``; score each by rendered gain on the
    planner-facing map; try them best first with OMPL (RRT-Connect in the platform's space,
    checked against the same map) until one is feasible within the budget. The rover tries
    candidates near where it dithered lately last (:meth:`MotionModel.stale`): the gain of
    a few novel points that its views never count as seen otherwise holds it in one place.
    """

    def plan(self, step: int, occupancy: PlannerMap, T_map_base: Pose,
             free: FreeSpace | None = None, contacts: np.ndarray | None = None,
             terrain: TerrainMap | None = None) -> PlanResult:
        cfg, pc = self.cfg, self.cfg.planner
        model, rng, field = self._setup(step, occupancy, T_map_base, free, contacts, terrain)
        rejected: list = []
        found = best_feasible(cfg, step, model, field, model.sample(rng, pc.n_candidates),
                              rejected)
        return found or fallback(step, model, T_map_base, rejected)

    @staticmethod
    def _to_path(step: int, states: list, model: MotionModel) -> PlanPath:
        return PlanPath(step, [model.base_pose(s) for s in states])


@dataclass
class _Trajectory:
    """A node of the beam: states from the current one, what their views saw, and the score."""

    states: list
    seen: np.ndarray
    """(P,) bool over the gain primitives seen by the views of ``states[1:]``."""
    gain: float
    travel_m: float
    first: int
    """Index of its first motion among the first level's candidates."""


class BeamPlanner(Planner):
    """Long-horizon next best view, as the paper's fixed planner (MAGICIAN) searches.

    Beam search over candidate viewpoints: the first level samples ``n_candidates`` states
    within the motion budget of the current one; each later level samples ``beam_branch`` more
    from the end of each kept trajectory. Every straight segment is collision-checked against
    the planner-facing map (``segment_check_m`` apart), and a trajectory is scored by its
    cumulative rendered gain, each gain primitive counted once along it. After each level the
    ``beam_width`` best (then shortest) trajectories are kept. The first motion of the best
    trajectory is planned with OMPL on the same map and executed; the next step replans from
    the new observations. If OMPL finds no path within the budget, the first motions of the
    other trajectories are tried in the order of their best continuation.
    """

    def plan(self, step: int, occupancy: PlannerMap, T_map_base: Pose,
             free: FreeSpace | None = None, contacts: np.ndarray | None = None,
             terrain: TerrainMap | None = None) -> PlanResult:
        cfg, pc = self.cfg, self.cfg.planner
        model, rng, field = self._setup(step, occupancy, T_map_base, free, contacts, terrain)
        dims = cfg.vehicle.dims

        def extend(nodes: list[_Trajectory], n: int) -> list[_Trajectory]:
            """The children of ``nodes``: ``n`` samples from the end of each, in turn, those
            whose segment is free, all their views rendered at once."""
            free = []
            for node in nodes:
                last = node.states[-1]
                for c in model.sample(rng, n, around=last):
                    if node is root:
                        model.refuse(c)  # (counted by hazard where the rover's layer refuses)
                    if model.segment_free(last, c):
                        free.append((node, c))
                    elif node is root:
                        blocked.append(c)  # no straight way there
            if len(nodes) == 1 and nodes[0] is root:
                free += [(root, c) for c in routed(blocked)]
            views = field.visible_many([model.camera(c) for _, c in free])
            out = []
            for (node, c), vis in zip(free, views, strict=True):
                seen = node.seen.copy()
                seen[vis] = True
                last = node.states[-1]
                weight = pc.beam_discount ** (len(node.states) - 1)
                out.append(_Trajectory(node.states + [c], seen,
                                       node.gain + weight * field.gain(vis, node.seen),
                                       node.travel_m + float(np.linalg.norm(
                                           np.subtract(c[:dims], last[:dims]))),
                                       node.first))
            return out

        def routed(candidates: list) -> list:
            """With ``route_blocked``: first motions with no straight way there that OMPL
            reaches within the motion budget (at most ``max_attempts`` of them tried, in the
            order sampled). On the rover most candidates lie behind something, and straight
            segments alone leave the beam only the ground it already knows."""
            if not pc.route_blocked:
                return []
            out = []
            for i, c in enumerate([c for c in candidates if model.is_free(c)]
                                  [: pc.max_attempts]):
                path = model.plan(model.current, c, seed=plan_seed(cfg, step, 10_000 + i))
                if path is not None and model.length(model.prefix + path) <= pc.max_step_m:
                    out.append(c)
            blocked[:] = [b for b in blocked if not any(b is c for c in out)]
            return out

        root = _Trajectory([model.current], np.zeros(len(field), dtype=bool), 0, 0.0, -1)
        blocked: list = []
        level = extend([root], pc.n_candidates)
        for i, t in enumerate(level):
            t.first = i
        firsts = list(level)
        best_of_first = {t.first: t.gain for t in level}  # best continuation of each first motion
        beam = sorted(level, key=lambda t: (-t.gain, t.travel_m))[: pc.beam_width]
        for _ in range(pc.beam_depth - 1):
            children = extend(beam, pc.beam_branch)
            if not children:
                break
            for c in children:
                best_of_first[c.first] = max(best_of_first[c.first], c.gain)
            beam = sorted(children, key=lambda t: (-t.gain, t.travel_m))[: pc.beam_width]
        avoid = model.avoid([t.states[1] for t in firsts])  # indexed by t.first
        order = sorted(firsts, key=lambda t: (int(avoid[t.first]), -best_of_first[t.first],
                                              t.travel_m))
        rejected = list(blocked)  # the first motions found blocked, then OMPL's failures
        for tried, t in enumerate(order[: pc.max_attempts]):
            goal = t.states[1]
            path = model.plan(model.current, goal, seed=plan_seed(cfg, step, tried))
            if (path is not None and model.length(model.prefix + path) <= pc.max_step_m
                    and model.admit(model.prefix + path) is None):
                return PlanResult(motion(step, path, model), int(best_of_first[t.first]),
                                  tried + 1, "best-feasible",
                                  GreedyPlanner._to_path(step, rejected, model))
            rejected.append(goal)
        # No first motion of the beam is feasible: before the fallback, the first level's
        # candidates not yet tried (those with no straight way there among them) go to OMPL
        # as the greedy planner sends its own, so the beam never stays where greedy would
        # move (crater/d, seed 1: the beam stayed 99 of 100 steps, greedy drove 158 m).
        rest = [t.states[1] for t in order[pc.max_attempts:]] + blocked
        rejected = [g for g in rejected if not any(g is b for b in blocked)]  # (tried again)
        found = best_feasible(cfg, step, model, field, rest, rejected, seed_base=20_000,
                              refuse=False)
        return found or fallback(step, model, T_map_base, rejected)


#: The built-in planners: ``--planner.name`` chooses (with those of :data:`PLANNER_GROUP`).
PLANNERS: dict[str, type[Planner]] = {"beam": BeamPlanner, "greedy": GreedyPlanner}

#: The entry-point group through which a package of your own adds planners, as pytest's
#: plugins and ROS 2's pluginlib do: in its pyproject.toml,
#: ``[project.entry-points."rovergate.planners"]`` then ``name = "package.module:Class"``,
#: a :class:`Planner` subclass. Installed next to rovergate, it is chosen by that name.
PLANNER_GROUP = "rovergate.planners"


def _registered() -> dict[str, importlib.metadata.EntryPoint]:
    """The installed packages' planners, by name (a built-in name or ``auto`` is not theirs
    to take: such an entry is left out, with a warning)."""
    found = {}
    for ep in importlib.metadata.entry_points(group=PLANNER_GROUP):
        if ep.name in PLANNERS or ep.name in ("auto", "cmd"):
            log.warning("planner entry point %r of %s is a built-in name; it is ignored",
                        ep.name, ep.value)
        else:
            found[ep.name] = ep
    return found


def planner_names() -> tuple[str, ...]:
    """Every planner ``--planner.name`` may choose (``auto`` aside): the built-in ones, then
    those installed packages register (:data:`PLANNER_GROUP`), without importing them."""
    return (*PLANNERS, *sorted(_registered()))


def planner_class(name: str) -> type[Planner]:
    """The planner class of ``name``: a built-in one, or the one an installed package
    registers (imported now). Anything else is refused with the names there are."""
    if name in PLANNERS:
        return PLANNERS[name]
    ep = _registered().get(name)
    if ep is None:
        raise UnknownNameError(f"unknown planner {name!r}; choose one of: auto, "
                               f"{', '.join(planner_names())} (--planner.name)")
    try:
        cls = ep.load()
    except Exception as exc:
        raise UnknownNameError(f"planner {name!r} ({ep.value}, entry point of "
                               f"{PLANNER_GROUP}) does not load: {type(exc).__name__}: "
                               f"{exc}") from exc
    if not (isinstance(cls, type) and issubclass(cls, Planner)):
        raise UnknownNameError(f"planner {name!r} ({ep.value}) is not a subclass of "
                               f"planner.planner.Planner; make it one")
    return cls


def planner_name(cfg: MissionConfig) -> str:
    """The planner a mission runs: ``auto`` is the platform's ``default_planner``, the beam on
    the flyer and the greedy planner on the rover (which the beam does not beat there:
    docs/performance.md, *Why `auto` gives the rover the greedy planner*)."""
    if cfg.planner.name == "auto":
        return cfg.vehicle.default_planner
    return cfg.planner.name


def make_planner(cfg: MissionConfig) -> Planner:
    """The configured planner; an unknown name gives the list of valid ones."""
    return planner_class(planner_name(cfg))(cfg)
