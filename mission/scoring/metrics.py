"""The study's metrics, on coverage curves and on what the gate withheld.

- C_T: the final coverage, the last value of the per-step curve over poses 0..T.
- AUC: :func:`mission.scoring.coverage.auc`, the area under that curve normalised to [0, 1].
- S70: :func:`s70`, the first step whose coverage reaches 70% of the learned baseline's final
  coverage for the same scene, start and repetition. A run that never reaches it counts as
  T + 1 (one step past the horizon, a censored value), and the study reports how many did not.
- The gate's audit (:func:`suppression_audit`, evaluation only): how many of the points the
  gate withheld were true false positives, farther than delta from the reference surface
  (precision), and how many of the prediction's false positives it withheld (recall).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from mission.scoring.coverage import auc

__all__ = ["auc", "final_coverage", "s70", "suppression_audit", "S70_FRACTION"]

S70_FRACTION = 0.7


def final_coverage(coverage: list[float] | np.ndarray) -> float:
    """C_T: the coverage after the last pose."""
    return float(coverage[-1]) if len(coverage) else 0.0


def s70(coverage: list[float] | np.ndarray, baseline_final: float,
        fraction: float = S70_FRACTION) -> tuple[int, bool]:
    """(step, reached): the first step t with coverage[t] >= fraction * baseline_final.

    Unreached within the curve's T + 1 poses, the step is T + 1 and ``reached`` is False.
    """
    c = np.asarray(coverage, dtype=np.float64)
    hit = np.flatnonzero(c >= fraction * baseline_final)
    if len(hit):
        return int(hit[0]), True
    return len(c), False


def _rows(points: np.ndarray) -> np.ndarray:
    """A 1-D view of (N, 3) float32 rows, for exact set operations on points."""
    p = np.ascontiguousarray(points, dtype=np.float32)
    return p.view(np.dtype((np.void, 12))).ravel()


def suppression_audit(predicted_xyz: np.ndarray, kept_xyz: np.ndarray,
                      reference_xyz: np.ndarray, delta_m: float,
                      reference_tree: cKDTree | None = None) -> tuple[int, int, int]:
    """(withheld, withheld false positives, false positives in the prediction) of one step.

    Withheld are the predicted points that did not reach the planner (``kept_xyz`` are the
    predicted points of the planner-facing map); a predicted point is a true false positive
    when no reference point lies within ``delta_m`` (the paper's oracle tag). The gate's
    suppression precision is the second over the first, its recall the second over the
    third. A mission passes ``reference_tree``, a k-d tree of ``reference_xyz`` built once.
    """
    if len(predicted_xyz) == 0:
        return 0, 0, 0
    withheld = ~np.isin(_rows(predicted_xyz), _rows(kept_xyz))
    if len(reference_xyz) == 0:
        false_positive = np.ones(len(predicted_xyz), dtype=bool)
    else:
        tree = reference_tree if reference_tree is not None else cKDTree(reference_xyz)
        d, _ = tree.query(predicted_xyz, distance_upper_bound=delta_m)
        false_positive = d > delta_m
    return (int(withheld.sum()), int(np.count_nonzero(withheld & false_positive)),
            int(false_positive.sum()))
