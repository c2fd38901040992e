"""The gate as a node of the graph (``MODULES["gate"]``): the planner-facing occupancy of the
mission's condition. Transport-free (see :mod:`rovergate.module`)."""

from __future__ import annotations

import logging
import time
from typing import Any, ClassVar

from gate.gate import Gate
from rovergate.conditions import get_condition
from rovergate.config import MissionConfig
from rovergate.graph import MODULES, Module
from rovergate.module import Ask, LogicDefaults, StepOutput
from rovergate.types import MapperOutput, xyz

log = logging.getLogger("rovergate.gate")


class GateLogic(LogicDefaults):
    """:class:`rovergate.module.ModuleLogic` of the gate."""

    spec: ClassVar[Module] = MODULES["gate"]

    def __init__(self, cfg: MissionConfig, ask: Ask | None = None) -> None:
        condition = get_condition(cfg.condition)
        reference = None
        if condition.needs_truth:
            # Oracle conditions only: the one place outside evaluation that asks for truth.
            if ask is None:
                raise ValueError(f"condition {condition.name} needs the reference occupancy")
            reference = xyz(ask("truth_occupancy"))
            log.info("oracle condition %s: %d reference points", condition.name, len(reference))
        self.gate = Gate(cfg.condition, cfg.gate, cfg.sensor, cfg.scene.d_scene_m,
                         cfg.scene.bounds_m, cfg.gate.view_tolerance_m, reference)

    def handle(self, step: int, inputs: dict[str, Any]) -> StepOutput:
        t0 = time.perf_counter()
        mapped = MapperOutput(step, inputs["surface"], inputs["predicted"])
        pose = inputs["pose"]  # with its covariance (sensor/pose_with_covariance)
        occupancy = self.gate.step(mapped, pose.pose, inputs["info"], inputs["depth"],
                                   pose.covariance)
        return StepOutput([("planner_map", occupancy)], {"gate": time.perf_counter() - t0})

    def restore(self, step: int, inputs: dict[str, Any]) -> None:
        pose = inputs["pose"]
        self.gate.restore(pose.pose, inputs["info"], inputs["depth"], pose.covariance)
