"""The gate's logic: build the planner-facing occupancy of a condition, every step."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from gate.filter import ObservationGate
from rovergate.conditions import get_condition
from rovergate.config import GateConfig, SensorConfig
from rovergate.spatial import kdtree
from rovergate.types import (
    PLANNER_DTYPE,
    CameraIntrinsics,
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
    """Composes S_t, the prediction and (oracle conditions only) ground truth for the planner."""

    def __init__(self, condition: str, cfg: GateConfig, sensor: SensorConfig, d_scene_m: float,
                 reference_xyz: np.ndarray | None = None, observed_radius_m: float = 0.0
                 ) -> None:
        self.condition = get_condition(condition)
        if self.condition.needs_truth and reference_xyz is None:
            raise ValueError(f"condition {condition!r} needs the reference occupancy")
        self.reference_xyz = reference_xyz
        self._reference_tree = cKDTree(reference_xyz) if reference_xyz is not None else None
        self.delta_m = cfg.oracle_delta_m(d_scene_m)
        self.observed_radius_m = observed_radius_m
        self.filter = ObservationGate(cfg.k, cfg.epsilon_m(d_scene_m), sensor.min_range_m,
                                      sensor.max_range_m)

    def restore(self, T_map_camera: Pose, intrinsics: CameraIntrinsics) -> None:
        """Take up a past frame without composing its map (a restarted gate replaying its
        past): its only state is the frustums so far, as U_t is recomputed every step."""
        self.filter.add_frustum(T_map_camera.matrix(), intrinsics)

    def step(self, mapped: MapperOutput, T_map_camera: Pose,
             intrinsics: CameraIntrinsics) -> PlannerMap:
        """The planner-facing occupancy of step t (the frame of step t is counted first)."""
        self.restore(T_map_camera, intrinsics)
        surface = mapped.surface
        s_xyz = xyz(surface)
        observed = make_cloud(s_xyz, PLANNER_DTYPE, source=Source.OBSERVED,
                              views=surface["views"])
        name = self.condition.name
        if name == "truth":
            # O* alone (equation 2), each point carrying the views of the nearest S_t point
            # within the planner's observed radius: what the reconstruction has seen, without
            # which every truth point would stay novel and draw the planner back for ever.
            ref = self.reference_xyz
            views = np.zeros(len(ref), dtype=np.uint16)
            if len(s_xyz) and self.observed_radius_m > 0:
                d, i = kdtree(s_xyz).query(ref, distance_upper_bound=self.observed_radius_m)
                hit = np.isfinite(d)
                views[hit] = surface["views"][i[hit]]
            return PlannerMap(mapped.step, make_cloud(ref, PLANNER_DTYPE, source=Source.TRUTH,
                                                      views=views))
        if name == "obs":
            return PlannerMap(mapped.step, observed)
        pred = xyz(mapped.predicted)
        keep = np.ones(len(pred), dtype=bool)
        extra = np.zeros((0, 3), dtype=np.float32)
        suppressed = 0
        if name == "gated":
            unsupported = self.filter.unsupported(pred, s_xyz)
            keep = ~unsupported
            suppressed = int(unsupported.sum())
        elif name in ("learned-fp", "learned+fn"):
            tags = oracle_tags(pred, self.reference_xyz, self.delta_m, self._reference_tree)
            if name == "learned-fp":
                keep = ~tags.false_positive
            else:
                extra = tags.false_negative_points
        parts = [observed,
                 make_cloud(pred[keep], PLANNER_DTYPE, source=Source.PREDICTED),
                 make_cloud(extra, PLANNER_DTYPE, source=Source.ORACLE_FN)]
        return PlannerMap(mapped.step, np.concatenate(parts), suppressed)
