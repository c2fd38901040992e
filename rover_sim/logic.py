"""The simulator as a node of the graph (``MODULES["sim"]``): drives the path of step t-1,
renders step t, serves ground truth on request. Transport-free: a process runs it under
:class:`rovergate.node.ModuleNode`, the in-process loop calls it directly."""

from __future__ import annotations

import time
from typing import Any, ClassVar

import numpy as np

from rover_sim.sim import RoverSim
from rovergate.config import MissionConfig
from rovergate.geometry import HAZCAMS
from rovergate.graph import MODULES, Module
from rovergate.module import Ask, StepOutput
from rovergate.types import XYZ_DTYPE, CameraIntrinsics, PoseWithCovariance, make_cloud


class SimLogic:
    """:class:`rovergate.module.ModuleLogic` of the simulator."""

    spec: ClassVar[Module] = MODULES["sim"]

    def __init__(self, cfg: MissionConfig, ask: Ask | None = None) -> None:
        self.sim = RoverSim(cfg)
        h = cfg.hazcam
        self.hazcam_info = CameraIntrinsics.from_fov(h.width_px, h.height_px, h.vfov_deg)

    def handle(self, step: int, inputs: dict[str, Any]) -> StepOutput:
        out = StepOutput()
        if step > 0:
            t0 = time.perf_counter()
            out.messages.append(("execution", self.sim.execute(inputs["path"])))
            out.stages["execute"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        frame = self.sim.render(step)
        out.stages["render"] = time.perf_counter() - t0
        out.messages += [("depth", (step, frame.depth_m)),
                         ("camera_info", (step, frame.intrinsics)),
                         ("pose", (step, frame.T_map_camera)),
                         ("pose_cov", (step, PoseWithCovariance(frame.T_map_camera,
                                                                frame.covariance)))]
        for end in HAZCAMS:  # 0 x 0 where the platform has none
            out.messages += [(f"hazcam_{end}", (step, frame.hazcams.get(
                                 end, np.zeros((0, 0), dtype=np.float32)))),
                             (f"hazcam_{end}_info", (step, self.hazcam_info))]
        out.messages.append(("base_pose", (step, frame.T_map_base)))
        return out

    def restore(self, step: int, inputs: dict[str, Any]) -> None:
        self.sim.restore(step, inputs["path"])

    def serve(self, topic: str) -> Any:
        # Ground truth is served on request only; under obs, learned and gated only the
        # mission's coverage evaluator asks.
        points = {"truth_surface": self.sim.truth_surface,
                  "truth_occupancy": self.sim.truth_occupancy}[topic]()
        return 0, make_cloud(points, XYZ_DTYPE)

    def close(self) -> None:
        self.sim.close()
