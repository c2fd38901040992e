"""The planner as a process: planner-facing occupancy and rover pose in, a path out."""

from __future__ import annotations

import time
from typing import Any

from planner.planner import make_planner
from rovergate.config import MissionConfig
from rovergate.logs import init_logging
from rovergate.node import Input, ModuleNode


def main(cfg: MissionConfig, resume_step: int = 0) -> int:
    log = init_logging("planner")
    planner = make_planner(cfg)
    node = ModuleNode("planner", cfg.session,
                      inputs={"map": Input("planner_map"), "base": Input("base_pose")},
                      outputs=["path"], log=log)

    def handle(step: int, inputs: dict[str, Any]) -> dict[str, float]:
        t0 = time.perf_counter()
        result = planner.plan(step, inputs["map"], inputs["base"])
        seconds = time.perf_counter() - t0
        log.debug("step %d: %s, gain %d after %d attempts", step, result.reason, result.gain,
                  result.attempts)
        node.publish("path", result.path)
        return {"plan": seconds}

    # A planner keeps no state between steps (its random draws are seeded by seed and step):
    # a restarted one needs only the inputs of the step it resumes at.
    return node.run(handle, cfg.ready_timeout_s + cfg.step_timeout_s, last_step=cfg.steps - 1,
                    resume_step=resume_step)
