"""The planner-facing occupancy conditions, the vocabulary the mapper, the gate, the study and
the ground commands share
(paper, equation 2, plus the gate of equation 4).

With S_t the observed surface, O_hat_t the thresholded prediction, FP_t / FN_t the oracle-tagged
errors at delta = 0.03 d_scene, and O* the reference occupied samples:

========== ==================================== ==========================================
name        planner receives                      needs
========== ==================================== ==========================================
obs         S_t                                   --
learned-fp  S_t + (O_hat_t - FP_t)                prediction, ground truth (oracle)
learned     S_t + O_hat_t                         prediction
learned+fn  S_t + O_hat_t + FN_t                  prediction, ground truth (oracle)
truth       O*                                    ground truth (oracle)
gated       S_t + (O_hat_t - U_t)                 prediction
gated-ray   S_t + (O_hat_t - U_ray_t)             prediction, depth of every frame
gated-pose  S_t + (O_hat_t - U_pose_t)            prediction, each pose's covariance
gated-split gain: S_t + (O_hat_t - U_ray_t);       prediction, depth of every frame
            collision: S_t + (O_hat_t - U_2view_t)
========== ==================================== ==========================================

U_ray_t is U_t with ray-consistent exposure: a frame counts only when the ray through the
point passed it by a margin on a usable return (gate/filter.py, RayGate); U_pose_t counts a
frame only if the point stays in its frustum under the pose's uncertainty, and widens support
by it (PoseGate); U_2view_t needs rays from two camera positions apart (SplitGate).
"""

from __future__ import annotations

from dataclasses import dataclass

from rovergate.errors import UnknownNameError


@dataclass(frozen=True)
class Condition:
    """One way of building the planner-facing occupancy."""

    name: str
    doc: str
    needs_prediction: bool
    needs_truth: bool
    withholds: bool = False
    """It passes on only part of the prediction, by a gate (evaluation audits what it
    withheld)."""


CONDITIONS: dict[str, Condition] = {c.name: c for c in [
    Condition("obs", "accumulated observations only: S_t", False, False),
    Condition("learned-fp", "learned, oracle false positives removed", True, True),
    Condition("learned", "S_t with the thresholded learned prediction", True, False),
    Condition("learned+fn", "learned, oracle false negatives restored", True, True),
    Condition("truth", "reference occupancy O*", False, True),
    Condition("gated", "learned through the observation-gated filter (eq. 4)", True, False,
              withholds=True),
    Condition("gated-ray", "learned through the gate with ray-consistent exposure", True,
              False, withholds=True),
    Condition("gated-pose", "learned through the gate aware of the pose's uncertainty",
              True, False, withholds=True),
    Condition("gated-split", "learned with separate evidence for gain and collision", True,
              False, withholds=True),
]}


def get_condition(name: str) -> Condition:
    """The named condition; raises :class:`UnknownNameError` listing the valid ones."""
    if name not in CONDITIONS:
        raise UnknownNameError(f"unknown condition {name!r}; choose one of: "
                               f"{', '.join(CONDITIONS)} (--condition)")
    return CONDITIONS[name]
