"""The mapper as a process: depth in, S_t and the learned prediction out, every step."""

from __future__ import annotations

import time
from typing import Any

from mapper.mapper import Mapper
from rovergate.config import MissionConfig
from rovergate.logs import init_logging
from rovergate.node import Input, ModuleNode
from rovergate.types import SensorFrame


def main(cfg: MissionConfig, resume_step: int = 0) -> int:
    log = init_logging("mapper")
    mapper = Mapper.for_mission(cfg)
    inputs = {"depth": Input("depth"), "info": Input("camera_info"), "pose": Input("pose"),
              "base": Input("base_pose")}
    node = ModuleNode("mapper", cfg.session, inputs=inputs, outputs=["surface", "predicted"],
                      log=log)

    def frame(step: int, inputs: dict[str, Any]) -> SensorFrame:
        return SensorFrame(step, inputs["depth"], inputs["info"], inputs["pose"], inputs["base"])

    def handle(step: int, inputs: dict[str, Any]) -> dict[str, float]:
        t0 = time.perf_counter()
        out = mapper.step(frame(step, inputs))
        seconds = time.perf_counter() - t0
        node.publish("surface", (step, out.surface))
        node.publish("predicted", (step, out.predicted))
        return {"integrate": seconds}

    return node.run(handle, cfg.ready_timeout_s + cfg.step_timeout_s, last_step=cfg.steps,
                    resume_step=resume_step,
                    restore=lambda step, inputs: mapper.integrate(frame(step, inputs)),
                    restore_inputs=inputs)
