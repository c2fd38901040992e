"""The mapper as a process: depth in, S_t and the learned prediction out, every step."""

from __future__ import annotations

import time
from typing import Any

from mapper.mapper import Mapper
from rovergate.config import MissionConfig
from rovergate.logs import init_logging
from rovergate.node import Input, ModuleNode
from rovergate.types import SensorFrame


def main(cfg: MissionConfig) -> int:
    log = init_logging("mapper")
    mapper = Mapper.for_mission(cfg)
    node = ModuleNode("mapper", cfg.session,
                      inputs={"depth": Input("depth"), "info": Input("camera_info"),
                              "pose": Input("pose"), "base": Input("base_pose")},
                      outputs=["surface", "predicted"], log=log)

    def handle(step: int, inputs: dict[str, Any]) -> dict[str, float]:
        t0 = time.perf_counter()
        out = mapper.step(SensorFrame(step, inputs["depth"], inputs["info"], inputs["pose"],
                                      inputs["base"]))
        seconds = time.perf_counter() - t0
        node.publish("surface", (step, out.surface))
        node.publish("predicted", (step, out.predicted))
        return {"integrate": seconds}

    return node.run(handle, cfg.ready_timeout_s + cfg.step_timeout_s, last_step=cfg.steps)
