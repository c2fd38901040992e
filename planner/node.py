"""The planner as a node of the graph (``MODULES["planner"]``): planner-facing occupancy and
rover pose in, a path out. Transport-free (see :mod:`rovergate.module`)."""

from __future__ import annotations

import logging
import time
from typing import Any, ClassVar

from planner.planner import make_planner
from rovergate.config import MissionConfig
from rovergate.graph import MODULES, Module
from rovergate.module import Ask, LogicDefaults, StepOutput

log = logging.getLogger("rovergate.planner")


class PlannerNode(LogicDefaults):
    """:class:`rovergate.module.ModuleLogic` of the planner. It keeps no state between steps
    (its random draws are seeded by seed and step): a restarted one needs only the inputs of
    the step it resumes at."""

    spec: ClassVar[Module] = MODULES["planner"]

    def __init__(self, cfg: MissionConfig, ask: Ask | None = None) -> None:
        self.planner = make_planner(cfg)

    def handle(self, step: int, inputs: dict[str, Any]) -> StepOutput:
        t0 = time.perf_counter()
        result = self.planner.plan(step, inputs["map"], inputs["base"])
        seconds = time.perf_counter() - t0
        log.debug("step %d: %s, gain %d after %d attempts", step, result.reason, result.gain,
                  result.attempts)
        return StepOutput([("rejected", result.rejected), ("path", result.path)],
                          {"plan": seconds})
