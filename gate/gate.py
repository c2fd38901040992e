"""The gate's logic: build the planner-facing occupancy of a condition, every step."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from gate.filter import ObservationGate, PoseGate, RayGate, SplitGate
from gate.views import ViewCounter, as_views
from rovergate.conditions import get_condition
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
        eps, near, far = cfg.epsilon_m(d_scene_m), sensor.min_range_m, sensor.max_range_m
        self.filter = {
            "gated-ray": lambda: RayGate(cfg.k, eps, near, far, cfg.ray_margin_m,
                                         cfg.ray_grazing_max_deg),
            "gated-pose": lambda: PoseGate(cfg.k, eps, near, far, cfg.pose_sigmas),
            "gated-split": lambda: SplitGate(cfg.k, eps, near, far, cfg.ray_margin_m,
                                             cfg.ray_grazing_max_deg, cfg.split_baseline_m),
        }.get(condition, lambda: ObservationGate(cfg.k, eps, near, far))()
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
        name = self.condition.name
        if name == "truth":
            ref = self.reference_xyz  # O* alone (equation 2)
            return PlannerMap(mapped.step, make_cloud(
                ref, PLANNER_DTYPE, source=Source.TRUTH,
                views=as_views(self.views.views_grown("truth", ref))))
        s_xyz = xyz(mapped.surface)
        observed = make_cloud(s_xyz, PLANNER_DTYPE, source=Source.OBSERVED,
                              views=as_views(self.views.views_grown("observed", s_xyz)))
        observed = observed[in_region(s_xyz, self.bounds_m)]
        if name == "obs":
            return PlannerMap(mapped.step, observed)
        pred = xyz(mapped.predicted)
        pred = pred[in_region(pred, self.bounds_m)]
        keep = np.ones(len(pred), dtype=bool)
        channels = np.full(len(pred), Channel.BOTH, dtype=np.uint8)
        extra = np.zeros((0, 3), dtype=np.float32)
        suppressed = 0
        if name == "gated-split":
            no_gain, no_collision = self.filter.withheld(pred, s_xyz)
            channels -= (no_gain * Channel.GAIN + no_collision * Channel.COLLISION).astype(
                np.uint8)
            keep = channels != 0
            suppressed = int(no_gain.sum())
        elif self.condition.withholds:
            unsupported = self.filter.unsupported(pred, s_xyz)
            keep = ~unsupported
            suppressed = int(unsupported.sum())
        elif name in ("learned-fp", "learned+fn"):
            tags = oracle_tags(pred, self.reference_xyz, self.delta_m, self._reference_tree)
            if name == "learned-fp":
                keep = ~tags.false_positive
            else:
                extra = tags.false_negative_points
        pred = pred[keep]
        parts = [observed,
                 make_cloud(pred, PLANNER_DTYPE, source=Source.PREDICTED,
                            views=as_views(self.views.views_keyed("predicted", pred)),
                            channels=channels[keep]),
                 make_cloud(extra, PLANNER_DTYPE, source=Source.ORACLE_FN,
                            views=as_views(self.views.views_keyed("oracle", extra)))]
        return PlannerMap(mapped.step, np.concatenate(parts), suppressed)
