"""The closed loop in one process, without Zenoh: the same logic, the same numbers."""

from __future__ import annotations

import time

from scipy.spatial import cKDTree

from gate.conditions import get_condition
from gate.gate import Gate, observed_radius_m
from mapper.mapper import Mapper
from mission.coverage import CoverageEvaluator
from mission.metrics import suppression_audit
from mission.record import MissionRecord
from planner.planner import make_planner
from rover_sim.sim import RoverSim
from rovergate.config import MissionConfig
from rovergate.types import Source, xyz


def run_in_process(cfg: MissionConfig, on_step=None) -> MissionRecord:
    """Run ``cfg.steps`` planning steps; ``on_step(t, coverage)`` is called after each pose."""
    record = MissionRecord(mode="in-process")
    t_start = time.perf_counter()
    sim = RoverSim(cfg)
    try:
        mapper = Mapper.for_mission(cfg)
        reference = sim.truth_occupancy() if get_condition(cfg.condition).needs_truth else None
        gate = Gate(cfg.condition, cfg.gate, cfg.sensor, cfg.scene.d_scene_m, reference,
                    observed_radius_m=observed_radius_m(cfg))
        planner = make_planner(cfg)
        evaluator = CoverageEvaluator(sim.truth_surface(), cfg.eval.tau_frac * cfg.scene.d_scene_m)
        # Evaluation only: which of the points the gate withheld were true false positives.
        audit_ref = sim.truth_occupancy() if cfg.condition == "gated" else None
        audit_tree = cKDTree(audit_ref) if audit_ref is not None else None
        delta_m = cfg.gate.oracle_delta_frac * cfg.scene.d_scene_m

        def timed(stage, fn, *args):
            t0 = time.perf_counter()
            out = fn(*args)
            record.add_stage(stage, time.perf_counter() - t0)
            return out

        t_step = time.perf_counter()
        path = None
        for t in range(cfg.steps + 1):
            if path is not None:
                record.executions.append(timed("execute", sim.execute, path))
                record.step_wall_s.append(time.perf_counter() - t_step)
                t_step = time.perf_counter()
            frame = timed("render", sim.render, t)
            mapped = timed("integrate", Mapper.step, mapper, frame)
            record.base_xy.append((float(frame.T_map_base.position[0]),
                                   float(frame.T_map_base.position[1])))
            record.coverage.append(evaluator.update(xyz(mapped.surface)))
            if on_step:
                on_step(t, record.coverage[-1])
            if t == cfg.steps:
                record.surface_xyz = xyz(mapped.surface)
                break
            occupancy = timed("gate", gate.step, mapped, frame.T_map_camera, frame.intrinsics)
            record.suppressed.append(occupancy.suppressed)
            record.predicted_points.append(len(mapped.predicted))
            kept = occupancy.points[occupancy.points["source"] == Source.PREDICTED]
            record.planner_predicted.append(len(kept))
            if audit_ref is not None:
                record.suppressed_fp.append(
                    suppression_audit(xyz(mapped.predicted), xyz(kept), audit_ref, delta_m,
                                      audit_tree)[1])
            path = timed("plan", planner.plan, t, occupancy, frame.T_map_base).path
            record.paths.append(path)
    finally:
        sim.close()
    record.wall_s = time.perf_counter() - t_start
    return record
