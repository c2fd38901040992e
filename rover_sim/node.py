"""The simulator as a process: renders each tick, executes each path, serves ground truth."""

from __future__ import annotations

import time
from typing import Any

from rover_sim.sim import RoverSim
from rovergate.config import MissionConfig
from rovergate.logs import init_logging
from rovergate.node import Input, ModuleNode
from rovergate.types import XYZ_DTYPE, make_cloud


def main(cfg: MissionConfig, resume_step: int = 0) -> int:
    log = init_logging("sim")
    sim = RoverSim(cfg)
    node = ModuleNode("sim", cfg.session,
                      inputs={"tick": Input("status"), "path": Input("path", lag=1)},
                      outputs=["depth", "camera_info", "pose", "base_pose", "execution"], log=log)
    # Ground truth is served on request only; under obs, learned and gated nobody asks.
    node.serve("truth_surface", lambda: (0, make_cloud(sim.truth_surface(), XYZ_DTYPE)))
    node.serve("truth_occupancy", lambda: (0, make_cloud(sim.truth_occupancy(), XYZ_DTYPE)))

    def handle(step: int, inputs: dict[str, Any]) -> dict[str, float]:
        stages = {}
        if step > 0:
            t0 = time.perf_counter()
            report = sim.execute(inputs["path"])
            stages["execute"] = time.perf_counter() - t0
            node.publish("execution", report)
        t0 = time.perf_counter()
        frame = sim.render(step)
        stages["render"] = time.perf_counter() - t0
        node.publish("depth", (step, frame.depth_m))
        node.publish("camera_info", (step, frame.intrinsics))
        node.publish("pose", (step, frame.T_map_camera))
        node.publish("base_pose", (step, frame.T_map_base))
        return stages

    try:
        return node.run(handle, cfg.ready_timeout_s + cfg.step_timeout_s, last_step=cfg.steps,
                        resume_step=resume_step,
                        restore=lambda step, inputs: sim.restore(step, inputs["path"]),
                        restore_inputs={"path": Input("path", lag=1)})
    finally:
        sim.close()
