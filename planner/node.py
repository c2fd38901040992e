"""The planner as a node of the graph (``MODULES["planner"]``): planner-facing occupancy and
rover pose in, a path out. Transport-free (see :mod:`rovergate.module`)."""

from __future__ import annotations

import logging
import time
from typing import Any, ClassVar

import numpy as np

from planner.freespace import FreeSpace
from planner.planner import make_planner
from planner.platforms import flyer_altitudes
from rovergate.config import MissionConfig
from rovergate.graph import MODULES, Module
from rovergate.module import Ask, LogicDefaults, StepOutput

log = logging.getLogger("rovergate.planner")


class PlannerNode(LogicDefaults):
    """:class:`rovergate.module.ModuleLogic` of the planner. Its random draws are seeded by
    seed and step; its state is what the platform learnt by moving: the flyer's known free
    space (carved from every frame so far and where the flyer has been) and the points where
    it touched the scene (reported with each execution, as a bumper would), which a restarted
    planner rebuilds by replaying them."""

    spec: ClassVar[Module] = MODULES["planner"]

    def __init__(self, cfg: MissionConfig, ask: Ask | None = None) -> None:
        self.cfg = cfg
        self.planner = make_planner(cfg)
        self.contacts: list[tuple[float, float, float]] = []
        """Where the platform touched the scene so far (its bumper): obstacles from now on."""
        self.free = None
        if cfg.platform == "flyer" and cfg.planner.known_free_only:
            b, s = cfg.scene.bounds_m, cfg.sensor
            lo, hi = flyer_altitudes(cfg)
            self.free = FreeSpace((b[0], b[1], lo, b[3], b[4], hi),
                                  cfg.planner.free_voxel_m, s.min_range_m, s.max_range_m)

    def restore(self, step: int, inputs: dict[str, Any]) -> None:
        report = inputs.get("execution")
        if report is not None and report.contact is not None:
            self.contacts.append(report.contact)
        if self.free is not None:
            self.free.add_frame(inputs["pose"].matrix(), inputs["info"], inputs["depth"])
            self.free.add_body(inputs["base"].position, self.cfg.flyer.radius_m)

    def handle(self, step: int, inputs: dict[str, Any]) -> StepOutput:
        t0 = time.perf_counter()
        self.restore(step, inputs)
        result = self.planner.plan(step, inputs["map"], inputs["base"], self.free,
                                   np.array(self.contacts, dtype=np.float32).reshape(-1, 3))
        seconds = time.perf_counter() - t0
        log.debug("step %d: %s, gain %d after %d attempts", step, result.reason, result.gain,
                  result.attempts)
        return StepOutput([("rejected", result.rejected), ("path", result.path)],
                          {"plan": seconds})
