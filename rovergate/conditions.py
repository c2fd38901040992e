"""The planner-facing occupancy conditions, the vocabulary the mapper, the gate, the study and
the ground commands share
(paper, equation 2, plus the gate of equation 4).

With S_t the observed surface, O_hat_t the thresholded prediction, FP_t / FN_t the oracle-tagged
errors at delta = 0.03 d_scene, and O* the reference occupied samples:

============== ======================================= ======================================
name           planner receives                        needs
============== ======================================= ======================================
obs            S_t                                     --
learned-fp     S_t + (O_hat_t - FP_t)                  prediction, ground truth (oracle)
learned        S_t + O_hat_t                           prediction
learned+fn     S_t + O_hat_t + FN_t                    prediction, ground truth (oracle)
truth          O*                                      ground truth (oracle)
gated          S_t + (O_hat_t - U_t)                   prediction
gated-ray      S_t + (O_hat_t - U_ray_t)               prediction, depth of every frame
gated-ray-inf  S_t + (O_hat_t - U_inf_t)               prediction, depth of every frame
gated-pose     S_t + (O_hat_t - U_pose_t)              prediction, each pose's covariance
gated-split    gain: S_t + (O_hat_t - U_ray_t);        prediction, depth of every frame
               collision: S_t + (O_hat_t - U_2view_t)
============== ======================================= ======================================

U_ray_t is U_t with ray-consistent exposure: a frame counts only when the ray through the
point passed it by a margin on a usable return (gate/filter.py, RayGate); U_inf_t also counts
a return beyond range (+Inf) as the ray's passage; U_pose_t counts a
frame only if the point stays in its frustum under the pose's uncertainty, and widens support
by it (PoseGate); U_2view_t needs rays from two camera positions apart (SplitGate).
"""

from __future__ import annotations

import functools
import importlib.metadata
import logging
from dataclasses import dataclass
from typing import Any

from rovergate.errors import ConfigError, UnknownNameError

log = logging.getLogger("rovergate.conditions")


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
    Condition("gated-ray-inf", "the ray gate reading a return beyond range as the ray's "
              "passage", True, False, withholds=True),
    Condition("gated-pose", "learned through the gate aware of the pose's uncertainty",
              True, False, withholds=True),
    Condition("gated-split", "learned with separate evidence for gain and collision", True,
              False, withholds=True),
]}


#: The entry-point group through which a package of your own adds a condition (as
#: ``rovergate.planners`` adds planners): in its pyproject.toml,
#: ``[project.entry-points."rovergate.conditions"]`` then ``name = "package.module:OBJECT"``,
#: an object with a ``condition`` (a :class:`Condition` of that name) and a ``variant`` (a
#: :class:`gate.gate.Variant`: its filter and what it keeps of the prediction; None for a
#: condition that passes on no prediction). A built-in name stays the built-in one.
CONDITION_GROUP = "rovergate.conditions"


@functools.cache
def _registered() -> dict[str, importlib.metadata.EntryPoint]:
    found = {}
    for ep in importlib.metadata.entry_points(group=CONDITION_GROUP):
        if ep.name in CONDITIONS:
            log.warning("condition entry point %r of %s is a built-in name; it is ignored",
                        ep.name, ep.value)
        else:
            found[ep.name] = ep
    return found


@functools.cache
def registered(name: str) -> Any:
    """The object a package registered as condition ``name`` (its ``condition`` and
    ``variant``), checked; raises :class:`ConfigError` in one line when it is not one."""
    ep = _registered()[name]
    obj = ep.load()
    condition = getattr(obj, "condition", None)
    if not isinstance(condition, Condition) or condition.name != name \
            or not hasattr(obj, "variant"):
        raise ConfigError(f"condition {name!r} ({ep.value}) needs a `condition` (a "
                          f"rovergate.conditions.Condition named {name!r}) and a `variant` "
                          "(a gate.gate.Variant, or None)")
    return obj


def condition_names() -> list[str]:
    """Every condition's name: the built-in ones, then those installed packages register."""
    return [*CONDITIONS, *_registered()]


def get_condition(name: str) -> Condition:
    """The named condition; raises :class:`UnknownNameError` listing the valid ones."""
    if name in CONDITIONS:
        return CONDITIONS[name]
    if name in _registered():
        condition: Condition = registered(name).condition
        return condition
    raise UnknownNameError(f"unknown condition {name!r}; choose one of: "
                           f"{', '.join(condition_names())} (--condition)")
