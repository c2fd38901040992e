"""The mapper as a node of the graph (``MODULES["mapper"]``): depth in, S_t and the learned
prediction out, every step. Transport-free (see :mod:`rovergate.module`)."""

from __future__ import annotations

import time
from typing import Any, ClassVar

from mapper.mapper import Mapper
from rovergate.config import MissionConfig
from rovergate.graph import MODULES, Module
from rovergate.module import Ask, LogicDefaults, StepOutput
from rovergate.types import SensorFrame


class MapperLogic(LogicDefaults):
    """:class:`rovergate.module.ModuleLogic` of the mapper."""

    spec: ClassVar[Module] = MODULES["mapper"]

    def __init__(self, cfg: MissionConfig, ask: Ask | None = None) -> None:
        self.mapper = Mapper.for_mission(cfg)

    @staticmethod
    def frame(step: int, inputs: dict[str, Any]) -> SensorFrame:
        hazcams = {end: inputs[end] for end in ("front", "rear") if inputs.get(end) is not None}
        return SensorFrame(step, inputs["depth"], inputs["info"], inputs["pose"], inputs["base"],
                           hazcams=hazcams)

    def handle(self, step: int, inputs: dict[str, Any]) -> StepOutput:
        t0 = time.perf_counter()
        out = self.mapper.step(self.frame(step, inputs))
        return StepOutput([("surface", (step, out.surface)), ("predicted", (step, out.predicted))],
                          {"integrate": time.perf_counter() - t0})

    def restore(self, step: int, inputs: dict[str, Any]) -> None:
        self.mapper.integrate(self.frame(step, inputs))
