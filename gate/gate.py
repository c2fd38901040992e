"""The gate's logic: build the planner-facing occupancy of a condition, every step."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree

from gate.filter import ObservationGate, PoseGate, RayGate, SplitGate
from gate.views import ViewCounter, as_views
from rovergate.conditions import CONDITIONS, get_condition, registered
from rovergate.config import GateConfig, SensorConfig
from rovergate.geometry import in_region
from rovergate.spatial import kdtree
from rovergate.types import (
    PLANNER_DTYPE,
    CameraIntrinsics,
    Channel,
    MapperOutput,
    PlannerMap,
    Pose,
    Source,
    make_cloud,
    xyz,
)


@dataclass
class OracleTags:
    """Oracle error sets of one step (ground truth: diagnostic conditions only)."""

    false_positive: np.ndarray
    """(M,) bool over the prediction: farther than delta from the reference surface."""
    false_negative_points: np.ndarray
    """(K, 3) float32 reference points with no prediction within delta."""


def oracle_tags(predicted_xyz: np.ndarray, reference_xyz: np.ndarray, delta_m: float,
                reference_tree: cKDTree | None = None) -> OracleTags:
    """Tag FP_t and FN_t as the paper does, at tolerance delta (``reference_tree``: a k-d tree
    of ``reference_xyz`` built once, as the reference does not change)."""
    if len(predicted_xyz) == 0:
        return OracleTags(np.zeros(0, dtype=bool), reference_xyz.copy())
    tree = reference_tree if reference_tree is not None else kdtree(reference_xyz)
    d_pred, _ = tree.query(predicted_xyz, distance_upper_bound=delta_m)
    d_ref, _ = kdtree(predicted_xyz).query(reference_xyz, distance_upper_bound=delta_m)
    return OracleTags(d_pred > delta_m, reference_xyz[d_ref > delta_m])


class Gate:
    """Composes S_t, the prediction and (oracle conditions only) ground truth for the planner.

    Everything it passes on lies in the scored region (:func:`rovergate.geometry.in_region`),
    and every point carries its views under one rule (:mod:`gate.views`).
    """

    def __init__(self, condition: str, cfg: GateConfig, sensor: SensorConfig, d_scene_m: float,
                 bounds_m: tuple[float, ...], view_tolerance_m: float,
                 reference_xyz: np.ndarray | None = None) -> None:
        self.condition = get_condition(condition)
        if self.condition.needs_truth and reference_xyz is None:
            raise ValueError(f"condition {condition!r} needs the reference occupancy")
        self.bounds_m = bounds_m
        if reference_xyz is not None:
            reference_xyz = reference_xyz[in_region(reference_xyz, bounds_m)]
        self.reference_xyz = reference_xyz
        self._reference_tree = cKDTree(reference_xyz) if reference_xyz is not None else None
        self.delta_m = cfg.oracle_delta_m(d_scene_m)
        self.variant = variant_of(condition)  # None: the map holds no prediction
        self.filter = (self.variant or VARIANTS["gated"]).make_filter(
            cfg, cfg.epsilon_m(d_scene_m), sensor.min_range_m, sensor.max_range_m)
        self.views = ViewCounter(sensor.min_range_m, sensor.max_range_m, view_tolerance_m)

    def restore(self, T_map_camera: Pose, intrinsics: CameraIntrinsics, depth: np.ndarray,
                covariance: np.ndarray | None = None) -> None:
        """Take up a past frame without composing its map (a restarted gate replaying its
        past): its only state is the frames so far (U_t and the views are recounted).
        ``covariance``: the (6, 6) covariance of ``T_map_camera`` (zeros if None)."""
        T = T_map_camera.matrix()
        self.filter.add_frame(T, intrinsics, depth, covariance)
        self.views.add_frame(T, intrinsics, depth)

    def step(self, mapped: MapperOutput, T_map_camera: Pose, intrinsics: CameraIntrinsics,
             depth: np.ndarray, covariance: np.ndarray | None = None) -> PlannerMap:
        """The planner-facing occupancy of step t (the frame of step t is counted first)."""
        self.restore(T_map_camera, intrinsics, depth, covariance)
        if self.variant is None and self.condition.needs_truth:
            ref = self.reference_xyz  # O* alone (equation 2)
            return PlannerMap(mapped.step, make_cloud(
                ref, PLANNER_DTYPE, source=Source.TRUTH,
                views=as_views(self.views.views_grown("truth", ref))))
        s_xyz = xyz(mapped.surface)
        observed = make_cloud(s_xyz, PLANNER_DTYPE, source=Source.OBSERVED,
                              views=as_views(self.views.views_grown("observed", s_xyz)))
        observed = observed[in_region(s_xyz, self.bounds_m)]
        if self.variant is None:  # S_t alone
            return PlannerMap(mapped.step, observed)
        pred = xyz(mapped.predicted)
        pred = pred[in_region(pred, self.bounds_m)]
        chosen = self.variant.select(self, pred, s_xyz)
        keep = chosen.channels != 0
        pred = pred[keep]
        parts = [observed,
                 make_cloud(pred, PLANNER_DTYPE, source=Source.PREDICTED,
                            views=as_views(self.views.views_keyed("predicted", pred)),
                            channels=chosen.channels[keep]),
                 make_cloud(chosen.extra, PLANNER_DTYPE, source=Source.ORACLE_FN,
                            views=as_views(self.views.views_keyed("oracle", chosen.extra)))]
        return PlannerMap(mapped.step, np.concatenate(parts), chosen.suppressed)


@dataclass
class Selection:
    """What a variant passes on of one step's prediction."""

    channels: np.ndarray
    """(M,) uint8 over the prediction: the planner's uses it serves (:class:`Channel`; 0:
    withheld from both)."""
    extra: np.ndarray = field(default_factory=lambda: np.zeros((0, 3), dtype=np.float32))
    """(K, 3) points added beside it (the oracle's false negatives)."""
    suppressed: int = 0
    """Predicted points a gate withheld from the gain (``PlannerMap.suppressed``)."""


def _all(pred: np.ndarray) -> np.ndarray:
    return np.full(len(pred), Channel.BOTH, dtype=np.uint8)


def everything(gate: Gate, pred: np.ndarray, surface: np.ndarray) -> Selection:
    """All of the prediction, to both uses (``learned``)."""
    return Selection(_all(pred))


def without_unsupported(gate: Gate, pred: np.ndarray, surface: np.ndarray) -> Selection:
    """The prediction less what the gate's filter finds unsupported (``gated`` and its
    ``-ray`` and ``-pose`` variants)."""
    unsupported = gate.filter.unsupported(pred, surface)  # U_t (equation 4) or its variant
    return Selection(np.where(unsupported, 0, Channel.BOTH).astype(np.uint8),
                     suppressed=int(unsupported.sum()))


def split_channels(gate: Gate, pred: np.ndarray, surface: np.ndarray) -> Selection:
    """Each predicted point to the uses its evidence allows (``gated-split``)."""
    assert isinstance(gate.filter, SplitGate)
    no_gain, no_collision = gate.filter.withheld(pred, surface)
    channels = _all(pred) - (no_gain * Channel.GAIN + no_collision * Channel.COLLISION).astype(
        np.uint8)
    return Selection(channels, suppressed=int(no_gain.sum()))


def without_false_positives(gate: Gate, pred: np.ndarray, surface: np.ndarray) -> Selection:
    """The prediction less its oracle false positives (``learned-fp``)."""
    tags = oracle_tags(pred, gate.reference_xyz, gate.delta_m, gate._reference_tree)
    return Selection(np.where(tags.false_positive, 0, Channel.BOTH).astype(np.uint8))


def with_false_negatives(gate: Gate, pred: np.ndarray, surface: np.ndarray) -> Selection:
    """All of the prediction and the oracle's false negatives beside it (``learned+fn``)."""
    tags = oracle_tags(pred, gate.reference_xyz, gate.delta_m, gate._reference_tree)
    return Selection(_all(pred), extra=tags.false_negative_points)


def frustum(cfg: GateConfig, eps: float, near: float, far: float) -> ObservationGate:
    """The frustum gate of equation 4 with the mission's K."""
    return ObservationGate(cfg.k, eps, near, far)


@dataclass(frozen=True)
class Variant:
    """How the gate builds the map of one condition that passes on the prediction: the
    filter that counts its exposures (given the gate's settings, epsilon and the sensor's
    range), and what it keeps of each step's prediction (given the gate, the prediction and
    S_t). A condition without a variant gets S_t alone, or O* alone when it reads the truth
    (``obs``, ``truth``)."""

    make_filter: Callable[[GateConfig, float, float, float], ObservationGate]
    select: Callable[[Gate, np.ndarray, np.ndarray], Selection]


#: The variant of each condition of :data:`rovergate.conditions.CONDITIONS` that passes on
#: the prediction, by its name (a test holds the two tables together).
VARIANTS: dict[str, Variant] = {
    "learned": Variant(frustum, everything),
    "learned-fp": Variant(frustum, without_false_positives),
    "learned+fn": Variant(frustum, with_false_negatives),
    "gated": Variant(frustum, without_unsupported),
    "gated-ray": Variant(lambda cfg, eps, near, far: RayGate(
        cfg.k, eps, near, far, cfg.ray_margin_m, cfg.ray_grazing_max_deg), without_unsupported),
    # Its own K and epsilon (GateConfig.ray_inf_*): eps is the frustum gate's, in metres.
    "gated-ray-inf": Variant(lambda cfg, eps, near, far: RayGate(
        cfg.ray_inf_k, eps * cfg.ray_inf_epsilon_frac / cfg.epsilon_frac, near, far,
        cfg.ray_margin_m, cfg.ray_grazing_max_deg, beyond_range_passes=True),
        without_unsupported),
    "gated-pose": Variant(lambda cfg, eps, near, far: PoseGate(
        cfg.k, eps, near, far, cfg.pose_sigmas), without_unsupported),
    "gated-split": Variant(lambda cfg, eps, near, far: SplitGate(
        cfg.k, eps, near, far, cfg.ray_margin_m, cfg.ray_grazing_max_deg,
        cfg.split_baseline_m), split_channels),
}


def variant_of(condition: str) -> Variant | None:
    """The variant of a condition: a built-in one's from :data:`VARIANTS`, a registered
    one's from its package (:data:`rovergate.conditions.CONDITION_GROUP`)."""
    if condition in CONDITIONS:
        return VARIANTS.get(condition)
    variant: Variant | None = registered(condition).variant
    return variant
