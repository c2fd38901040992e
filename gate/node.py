"""The gate as a process: builds the planner-facing occupancy of the mission's condition."""

from __future__ import annotations

import time
from typing import Any

from gate.conditions import get_condition
from gate.gate import Gate, observed_radius_m
from rovergate.config import MissionConfig
from rovergate.logs import init_logging
from rovergate.node import Input, ModuleNode
from rovergate.types import MapperOutput, xyz


def main(cfg: MissionConfig, resume_step: int = 0) -> int:
    log = init_logging("gate")
    condition = get_condition(cfg.condition)
    node = ModuleNode("gate", cfg.session,
                      inputs={"surface": Input("surface"), "predicted": Input("predicted"),
                              "pose": Input("pose"), "info": Input("camera_info")},
                      outputs=["planner_map"], log=log)
    reference = None
    if condition.needs_truth:
        # Oracle conditions only: the one place outside evaluation that asks for truth.
        try:
            reference = xyz(node.query("truth_occupancy", cfg.ready_timeout_s))
        except BaseException:
            node.close()
            raise
        log.info("oracle condition %s: %d reference points", condition.name, len(reference))
    gate = Gate(cfg.condition, cfg.gate, cfg.sensor, cfg.scene.d_scene_m, reference,
                observed_radius_m=observed_radius_m(cfg))

    def handle(step: int, inputs: dict[str, Any]) -> dict[str, float]:
        t0 = time.perf_counter()
        mapped = MapperOutput(step, inputs["surface"], inputs["predicted"])
        occupancy = gate.step(mapped, inputs["pose"], inputs["info"])
        seconds = time.perf_counter() - t0
        node.publish("planner_map", occupancy)
        return {"gate": seconds}

    return node.run(handle, cfg.ready_timeout_s + cfg.step_timeout_s, last_step=cfg.steps - 1,
                    resume_step=resume_step,
                    restore=lambda step, inputs: gate.restore(inputs["pose"], inputs["info"]),
                    restore_inputs={"pose": Input("pose"), "info": Input("camera_info")})
