"""The planner as a node of the graph (``MODULES["planner"]``): planner-facing occupancy and
rover pose in, a path out. Transport-free (see :mod:`rovergate.module`)."""

from __future__ import annotations

import logging
import time
from typing import Any, ClassVar

import numpy as np

from planner.freespace import FreeSpace
from planner.planner import counted_points, make_planner
from planner.platforms import flyer_altitudes
from planner.traversability import TerrainMap, driven_way
from rovergate.config import MissionConfig
from rovergate.graph import MODULES, Module
from rovergate.module import Ask, LogicDefaults, StepOutput
from rovergate.types import TraversabilityGrid, TraverseReport

log = logging.getLogger("rovergate.planner")


class PlannerLogic(LogicDefaults):
    """:class:`rovergate.module.ModuleLogic` of the planner. Its random draws are seeded by
    seed and step; its state is what the platform learnt by moving: the flyer's known free
    space (carved from every frame so far and where the flyer has been), the rover's
    traversability layer (its height map from every frame of the mast and hazard cameras,
    :mod:`planner.traversability`, with the way it came: its own last path, as far as the
    execution got) and the points where it touched the scene (reported with each execution,
    as a bumper would), which a restarted planner rebuilds by replaying them."""

    spec: ClassVar[Module] = MODULES["planner"]

    def __init__(self, cfg: MissionConfig, ask: Ask | None = None) -> None:
        self.cfg = cfg
        self.planner = make_planner(cfg)
        self.contacts: list[tuple[float, float, float]] = []
        """Where the platform touched the scene so far (its bumper): obstacles from now on."""
        self.free = None
        if cfg.vehicle.flies and cfg.planner.known_free_only:
            b, s = cfg.scene.bounds_m, cfg.sensor
            lo, hi = flyer_altitudes(cfg)
            self.free = FreeSpace((b[0], b[1], lo, b[3], b[4], hi),
                                  cfg.planner.free_voxel_m, s.min_range_m, s.max_range_m)
        self.terrain = (TerrainMap(cfg) if not cfg.vehicle.flies and cfg.traverse.enabled
                        else None)

    def restore(self, step: int, inputs: dict[str, Any]) -> None:
        report = inputs.get("execution")
        if report is not None and report.contact is not None:
            self.contacts.append(report.contact)
        if self.free is not None:
            self.free.add_frame(inputs["pose"].matrix(), inputs["info"], inputs["depth"])
            self.free.add_body(inputs["base"].position, self.cfg.flyer.radius_m)
        if self.terrain is not None:
            self.terrain.add_step(step, inputs["base"].matrix(),
                                  (inputs["pose"].matrix(), inputs["info"], inputs["depth"]),
                                  {"front": inputs.get("front"), "rear": inputs.get("rear")},
                                  driven_way(inputs.get("path"), report))

    def handle(self, step: int, inputs: dict[str, Any]) -> StepOutput:
        t0 = time.perf_counter()
        self.restore(step, inputs)
        before = dict(self.terrain.refused) if self.terrain is not None else {}
        if self.terrain is not None:
            x, y = inputs["base"].position[:2]
            self.terrain.prepare(float(x), float(y))
        t1 = time.perf_counter()
        result = self.planner.plan(step, inputs["map"], inputs["base"], self.free,
                                   np.array(self.contacts, dtype=np.float32).reshape(-1, 3),
                                   terrain=self.terrain)
        goal = result.path.poses[-1] if result.path.poses else inputs["base"]
        gain_points = counted_points(self.cfg, inputs["map"], goal,
                                     getattr(self.planner, "rendered", None))
        t2 = time.perf_counter()
        log.debug("step %d: %s, gain %d after %d attempts", step, result.reason, result.gain,
                  result.attempts)
        if self.terrain is not None:
            grid = self.terrain.grid(step)
            refused = {k: v - before.get(k, 0) for k, v in self.terrain.refused.items()}
            known = self.terrain.known_cells()
        else:
            grid = TraversabilityGrid(step, np.zeros((0, 0), dtype=np.int8),
                                      self.cfg.traverse.cell_m, (0.0, 0.0))
            refused, known = {}, 0
        report = TraverseReport(step, refused, result.reason, known, gain_points)
        return StepOutput([("traversability", grid), ("traverse", report),
                           ("rejected", result.rejected), ("path", result.path)],
                          {"traverse": t1 - t0, "plan": t2 - t1})
