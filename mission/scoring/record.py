"""What a mission records, whichever way it ran, and the metrics derived from it."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from mission.scoring.coverage import auc
from mission.scoring.evaluation import PLANNER_FAULT, UNSEEN, stuck_flags
from rovergate.types import ExecutionReport, PlanPath, TraverseReport


@dataclass
class MissionRecord:
    """Per-step history of one mission."""

    coverage: list[float] = field(default_factory=list)
    """Coverage after poses 0..T (T+1 values)."""
    base_xy: list[tuple[float, float]] = field(default_factory=list)
    """Rover base position at each pose 0..T."""
    base_z: list[float] = field(default_factory=list)
    """Its height at each pose 0..T."""
    collision_class: list[str | None] = field(default_factory=list)
    """Per motion 0..T-1: planner-fault, unseen-geometry or None (no collision); see
    :mod:`mission.scoring.evaluation`."""
    fp_gain_share: list[float | None] = field(default_factory=list)
    """Per step 0..T-1: share of the chosen view's gain from oracle false positives."""
    rejected_by_fp: list[int | None] = field(default_factory=list)
    """Per step 0..T-1: candidates rejected as infeasible because of oracle false positives."""
    executions: list[ExecutionReport] = field(default_factory=list)
    paths: list[PlanPath] = field(default_factory=list)
    traverse: list[TraverseReport] = field(default_factory=list)
    """Per step 0..T-1: what the rover's traversability layer refused, and the planner's
    choice (a planner of the user's own may not say)."""
    stage_s: dict[str, list[float]] = field(default_factory=dict)
    """Compute time of each stage (render, integrate, gate, plan, execute) per step."""
    step_wall_s: list[float] = field(default_factory=list)
    """Wall time of each step of the loop, as the mission clock saw it."""
    suppressed: list[int] = field(default_factory=list)
    """Predicted points the gate withheld from the planner at each step 0..T-1."""
    suppressed_fp: list[int] = field(default_factory=list)
    """Of those, the true false positives (evaluation only; gated runs)."""
    predicted_fp: list[int] = field(default_factory=list)
    """The prediction's true false positives at each step (evaluation only; gated runs)."""
    predicted_points: list[int] = field(default_factory=list)
    """Size of the thresholded prediction O_hat_t at each step 0..T-1."""
    planner_predicted: list[int] = field(default_factory=list)
    """Predicted points in the planner-facing map at each step 0..T-1."""
    surface_xyz: np.ndarray = field(default_factory=lambda: np.zeros((0, 3), np.float32))
    conditions: list[tuple[int, str]] = field(default_factory=list)
    """The condition the mission ran under, as (first step, condition): more than one entry
    when a ground command changed it during the mission."""
    restarts: list[dict] = field(default_factory=list)
    """Modules that died and were restarted (process set only): module, step, reason, and
    the seconds from the death to the module's token and to the loop resuming."""
    resumes: list[dict] = field(default_factory=list)
    """Each time the mission manager itself was restarted (``rovergate run --resume``): the
    step the loop resumed at and the seconds from the new manager's start to it."""
    link: dict = field(default_factory=dict)
    """The link to the ground (process set): link steps, items radiated and undelivered,
    ground commands and reconfigurations."""
    state: str = "done"
    """done, or aborted (by a ground command)."""
    wall_s: float = 0.0
    dropped_messages: int = 0
    mode: str = "in-process"
    recording: dict = field(default_factory=dict)
    """The flight recorder's bag (ecosystem/recorder.py): path, messages per topic, payload
    and file bytes, the writer's seconds; empty when not recorded."""

    def add_stage(self, stage: str, seconds: float) -> None:
        self.stage_s.setdefault(stage, []).append(seconds)

    def stuck(self) -> np.ndarray:
        """(T+1,) bool: stuck at each pose (:func:`mission.scoring.evaluation.stuck_flags`)."""
        pos = np.c_[np.array(self.base_xy, dtype=np.float64).reshape(-1, 2),
                    np.array(self.base_z, dtype=np.float64)]
        return stuck_flags(pos)

    def metrics(self) -> dict:
        """The figures of metrics.json."""
        med = {k: float(np.median(v)) for k, v in sorted(self.stage_s.items()) if v}
        stage_sum = np.zeros(len(self.step_wall_s))
        for name, values in self.stage_s.items():
            if name in ("render", "integrate", "gate", "traverse", "plan", "execute"):
                n = min(len(values), len(stage_sum))
                stage_sum[:n] += values[:n]
        transport = np.maximum(np.asarray(self.step_wall_s) - stage_sum, 0.0)
        shares = [s for s in self.fp_gain_share if s is not None]
        refused: dict[str, int] = {}
        reasons: dict[str, int] = {}
        for r in self.traverse:
            for k, v in r.refused.items():
                refused[k] = refused.get(k, 0) + v
            reasons[r.reason] = reasons.get(r.reason, 0) + 1
        return {
            "mode": self.mode,
            "steps": len(self.coverage) - 1,
            "coverage": self.coverage,
            "final_coverage": self.coverage[-1] if self.coverage else 0.0,
            "auc": auc(self.coverage),
            "collisions": int(sum(e.collided for e in self.executions)),
            "collisions_planner_fault": self.collision_class.count(PLANNER_FAULT),
            "collisions_unseen": self.collision_class.count(UNSEEN),
            "collision_class_per_step": self.collision_class,
            "stuck_steps": int(self.stuck().sum()),
            "fp_gain_share": (float(np.mean(shares)) if shares else None),
            "fp_gain_share_per_step": self.fp_gain_share,
            "rejected_by_fp": (int(sum(r for r in self.rejected_by_fp if r is not None))
                               if any(r is not None for r in self.rejected_by_fp) else None),
            "rejected_by_fp_per_step": self.rejected_by_fp,
            "min_clearance_m": float(min((e.min_clearance_m for e in self.executions),
                                         default=float("nan"))),
            "untraversable_stops": int(sum(e.untraversable for e in self.executions)),
            "min_clearance_per_step_m": [e.min_clearance_m for e in self.executions],
            "path_length_m": float(sum(e.path_length_m for e in self.executions)),
            "refused_by_hazard": {k: refused.get(k, 0) for k in
                                  ("unknown", "wheel-drop", "tilt", "belly")},
            "refused_per_step": [sum(r.refused.values()) for r in self.traverse],
            "plan_reasons": dict(sorted(reasons.items())),
            "backouts": reasons.get("backout", 0),
            "final_pose_error_m": (self.executions[-1].pose_error_m if self.executions
                                   else 0.0),
            "median_stage_s": med,
            "median_transport_s": float(np.median(transport)) if len(transport) else 0.0,
            "median_step_s": float(np.median(self.step_wall_s)) if self.step_wall_s else 0.0,
            "wall_s": self.wall_s,
            "dropped_messages": self.dropped_messages,
            "restarts": self.restarts,
            "manager_resumes": self.resumes,
            "state": self.state,
            "link": self.link,
            "recording": self.recording,
            "observed_points": int(len(self.surface_xyz)),
            "predicted_points_per_step": self.predicted_points,
            "planner_predicted_per_step": self.planner_predicted,
            "suppressed_per_step": self.suppressed,
            "suppressed_fp_per_step": self.suppressed_fp,
            "suppressed_fp_share": (sum(self.suppressed_fp) / sum(self.suppressed)
                                    if self.suppressed_fp and sum(self.suppressed) else None),
            # The gate's audit (evaluation only), per step and pooled over the mission:
            # precision = withheld false positives / withheld, recall = withheld false
            # positives / the prediction's false positives (None where undefined).
            "predicted_fp_per_step": self.predicted_fp,
            "suppression_precision_per_step": [
                fp / n if n else None for fp, n in zip(self.suppressed_fp, self.suppressed,
                                                       strict=False)],
            "suppression_recall_per_step": [
                fp / n if n else None for fp, n in zip(self.suppressed_fp, self.predicted_fp,
                                                       strict=True)],
            "suppression_recall": (sum(self.suppressed_fp) / sum(self.predicted_fp)
                                   if self.predicted_fp and sum(self.predicted_fp) else None),
            "wrongly_withheld_per_step": [n - fp for fp, n in zip(
                self.suppressed_fp, self.suppressed, strict=False)],
        }
