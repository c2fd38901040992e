"""Evaluation of each step against ground truth: what the vehicle hit and why, whether it is
stuck, and how oracle false positives steered the planner's decision. Evaluation only: nothing
here reaches a module.

- **Collision class.** A collision with the true scene is a *planner fault* when the map the
  planner was given held the geometry that was hit as an obstacle: a map point within the
  margin the planner keeps from map points (:func:`fault_tolerance_m`: 0.2 m for the flyer,
  0.15 m for the rover) of the contact point that the planner's collision model counts as an
  obstacle (the flyer: any map point; the rover: a point standing in its body's height band
  over the local ground, not ground). Otherwise it is *unseen geometry*: the map lacked it, or
  showed it as ground (a predicted ground voxel where a rock stands). Every executed motion is
  checked on the planner's map, so a planner fault means the check and the world disagree (a
  gap in the map's sampling of a surface, the body's kinematics) and is a bug to fix, not a
  finding. Under ``truth`` every collision is reported whatever its class; the study's bar is
  none at all there.
- **Stuck.** The vehicle is stuck at pose t (t >= ``STUCK_WINDOW``) when its net displacement
  over the last ``STUCK_WINDOW`` steps is under ``STUCK_MIN_M``.
- **The paper's decision-level measure.** Of the gain the planner rendered for the viewpoint
  it chose (the goal of its motion: the points it counted, which it reports in its
  ``TraverseReport``), the share that comes from oracle false positives (predicted points
  farther than delta from O*); and how many candidates it rejected as
  infeasible that were feasible on the same map without those false positives (their goal
  state free and the straight motion to it free: a lower bound, as OMPL is not re-run).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from planner.planner import counted_points, novel_mask
from planner.platforms import motion_model
from rovergate.config import MissionConfig
from rovergate.geometry import voxel_first_points
from rovergate.spatial import kdtree
from rovergate.types import (
    Channel,
    ExecutionReport,
    PlannerMap,
    PlanPath,
    Pose,
    Source,
    xyz,
)

STUCK_WINDOW = 10
"""Steps over which net progress is measured."""
STUCK_MIN_M = 0.5
"""Net displacement under which a vehicle counts as stuck over the window."""

PLANNER_FAULT = "planner-fault"
UNSEEN = "unseen-geometry"


def fault_tolerance_m(cfg: MissionConfig) -> float:
    """How near the contact an obstacle of the map must lie for a planner fault: the margin
    the planner keeps from map points (the flyer's sphere margin; the rover's obstacle box
    half-edge, 0.075 m, plus its body margin, 0.1 m, rounded to one obstacle voxel, 0.15 m)."""
    return cfg.planner.flyer_margin_m if cfg.vehicle.flies else cfg.planner.obstacle_voxel_m


def collision_class(report: ExecutionReport, planner_map: PlannerMap, cfg: MissionConfig,
                    T_map_base: Pose) -> str | None:
    """:data:`PLANNER_FAULT`, :data:`UNSEEN` or None (no collision); see the module
    docstring. ``T_map_base``: the pose the motion started from. A collision without a
    contact point (FCL gave none) counts as a planner fault, the class that must stay at
    zero."""
    if not report.collided:
        return None
    if report.contact is None:
        return PLANNER_FAULT
    planner_map = planner_map.serving(Channel.COLLISION)  # what the planner checked against
    points = xyz(planner_map.points)
    if not cfg.vehicle.flies and len(points):
        # What the rover's collision model counts as an obstacle (not the ground it reads).
        model = motion_model(cfg, points, T_map_base,
                             predicted=planner_map.points["source"] == Source.PREDICTED)
        points = model.ground.obstacle_xyz
    if len(points) == 0:
        return UNSEEN
    d, _ = kdtree(points).query(np.asarray(report.contact),
                                distance_upper_bound=fault_tolerance_m(cfg))
    return PLANNER_FAULT if np.isfinite(d) else UNSEEN


def stuck_flags(positions: np.ndarray, window: int = STUCK_WINDOW,
                min_m: float = STUCK_MIN_M) -> np.ndarray:
    """(T+1,) bool over poses: stuck at t (see the module docstring)."""
    p = np.asarray(positions, dtype=np.float64).reshape(len(positions), -1)
    out = np.zeros(len(p), dtype=bool)
    if len(p) > window:
        out[window:] = np.linalg.norm(p[window:] - p[:-window], axis=1) < min_m
    return out


@dataclass
class Decision:
    """How oracle false positives weighed on one step's decision."""

    fp_gain_share: float | None
    """Share of the chosen view's rendered gain from oracle false positives (0 when the map
    holds no novel false positive; None when the view had no gain to share)."""
    rejected_by_fp: int | None
    """Candidates rejected as infeasible that the map without false positives allows (None:
    the planner did not publish what it rejected)."""


class StepEvaluator:
    """The mission's evaluation of each step, with the reference occupancy O* built once."""

    def __init__(self, cfg: MissionConfig, truth_surface: np.ndarray) -> None:
        self.cfg = cfg
        self.reference = voxel_first_points(truth_surface, cfg.mapper.voxel_m)  # as the sim
        self.tree = cKDTree(self.reference)

    def false_positives(self, planner_map: PlannerMap) -> np.ndarray:
        """(N,) bool over the map: predicted points farther than delta from O*."""
        pts = planner_map.points
        fp = np.zeros(len(pts), dtype=bool)
        pred = np.flatnonzero(pts["source"] == Source.PREDICTED)
        if len(pred):  # the oracle's FP tag (gate.gate.oracle_tags), without its FN half
            d, _ = self.tree.query(xyz(pts[pred]), distance_upper_bound=self.cfg.oracle_delta_m)
            fp[pred] = d > self.cfg.oracle_delta_m
        return fp

    def decision(self, planner_map: PlannerMap, path: PlanPath, rejected: PlanPath | None,
                 T_map_base: Pose, contacts: np.ndarray | None = None,
                 gain_points: np.ndarray | None = None) -> Decision:
        """The decision measure of one step (``T_map_base``: the pose it planned from;
        ``rejected`` None: the planner does not say what it rejected; ``contacts``: the
        contact points the planner knew; ``gain_points``: the points of ``planner_map`` the
        gain of the chosen view counted, as the planner reported them in its
        ``TraverseReport``; None: a planner of the user's own that reports none, for which
        they are rendered here with the planner's own function)."""
        cfg = self.cfg
        # The share of gain on what the gain saw; the blocked candidates on what blocked them
        # (the two channels of the map, one and the same but under gated-split).
        fp = self.false_positives(planner_map)
        serving_gain = (planner_map.points["channels"] & Channel.GAIN) != 0
        novel = novel_mask(planner_map, cfg.planner.observed_min_views)
        share: float | None = 0.0  # no novel false positive the gain serves: no share of it
        if (fp & novel & serving_gain).any():
            if gain_points is None:
                goal = path.poses[-1] if path.poses else T_map_base
                gain_points = counted_points(cfg, planner_map, goal)
            share = (int(fp[gain_points].sum()) / len(gain_points) if len(gain_points)
                     else None)  # the view had no gain to share
        blocked = None if rejected is None else 0
        planner_map = planner_map.serving(Channel.COLLISION)
        fp = self.false_positives(planner_map)
        points = xyz(planner_map.points)
        if rejected is not None and fp.any() and rejected.poses:
            # Occupancy alone, on the map and on the map without its false positives, from
            # where the planner planned (its escape, its contacts; known free space does not
            # depend on the map, so it is left out of both).
            predicted = planner_map.points["source"] == Source.PREDICTED
            full = motion_model(cfg, points, T_map_base, predicted=predicted,
                                contacts=contacts)
            clean = motion_model(cfg, points[~fp], T_map_base, predicted=predicted[~fp],
                                 contacts=contacts)
            for model in (full, clean):
                model.leave_blocked_start()
            for pose in rejected.poses:
                g = clean.state_of(pose)
                if (not (full.is_free(g) and full.segment_free(full.current, g))
                        and clean.is_free(g) and clean.segment_free(clean.current, g)):
                    blocked += 1
        return Decision(share, blocked)
