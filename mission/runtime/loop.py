"""The mission loop, written once: the clock, the step order, coverage, the gate audit and the
record, driven over either transport (:mod:`mission.runtime.transport`).

Step t: the mission ticks t; the simulator drives the path of step t-1 and renders step t; the
mapper integrates it; the gate and the planner make the map and the path of step t. The
mission receives what it records of step t-1 (path, execution report, prediction, planner
map) and of step t (S_t, the base pose), and scores coverage. In the process set the link to
the ground runs at every step boundary (:class:`mission.link.operations.Operations`).
"""

from __future__ import annotations

import dataclasses
import logging
import time
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from mission.runtime.checkpoint import CheckpointWriter, LoopState
from mission.runtime.checkpoint import remove as remove_checkpoint
from mission.runtime.transport import InProcessTransport, Transport
from mission.scoring.coverage import CoverageEvaluator
from mission.scoring.evaluation import StepEvaluator, collision_class
from mission.scoring.metrics import suppression_audit
from mission.scoring.record import MissionRecord
from rovergate.conditions import get_condition
from rovergate.config import MissionConfig
from rovergate.geometry import in_region
from rovergate.module import STOP
from rovergate.types import Channel, MissionStatus, Source, xyz

if TYPE_CHECKING:
    from ecosystem.recorder import FlightRecorder
    from mission.link.operations import Operations
    from rovergate.taps import Taps

log = logging.getLogger("rovergate.mission")

OnStep = Callable[[int, float], None]


def run_mission(cfg: MissionConfig, transport: Transport, on_step: OnStep | None = None,
                operations_factory: Callable[[], Operations] | None = None,
                checkpoint: Path | None = None, resume: LoopState | None = None
                ) -> MissionRecord:
    """Run ``cfg.steps`` planning steps over ``transport``; ``on_step(t, coverage)`` is called
    after each pose. ``operations_factory`` (process set only) builds the ground link's
    :class:`mission.link.operations.Operations`. With ``checkpoint`` (a directory), the loop's
    state is saved there after every step (:mod:`mission.runtime.checkpoint`); ``resume`` is such a
    state to carry on from. Raises :class:`rovergate.errors.MissionFailed` on a fault.

    ``cfg`` is the launch configuration: what the mission is scored by (the steps, the scene,
    the evaluation's tolerances), which no command changes. What a ground command can change
    (the condition, the planner) the loop reads from one place, ``transport.cfg``, at every
    step boundary."""
    record = resume.record if resume else MissionRecord(mode=transport.mode)
    t_start = time.perf_counter()
    wall_before = resume.record.wall_s if resume else 0.0
    state = "failed"
    collisions = resume.collisions if resume else 0
    first = resume.step if resume else 0
    ops = None
    saver = CheckpointWriter(checkpoint, resume) if checkpoint is not None else None
    condition = resume.condition if resume else cfg.condition
    surface_xyz = None  # the last step's observed surface, for the report's top-down map
    try:
        ops = operations_factory() if operations_factory else None
        if ops and resume and resume.operations:
            ops.restore(resume.operations)
        transport.start()
        truth_surface = xyz(transport.ask("truth_surface"))
        evaluator = CoverageEvaluator(truth_surface, cfg.tau_m)
        # Evaluation only: O* (as the simulator derives it) to audit what the gate withheld,
        # to classify collisions and to weigh the planner's decisions (mission.scoring.evaluation).
        judge = StepEvaluator(cfg, truth_surface)
        previous_base = resume.previous_base if resume else None
        if ops and resume:
            ops.event(first, "mission-resumed",
                             f"the mission manager restarted; resuming at step {first} "
                             f"after {time.perf_counter() - t_start:.1f} s")
        elif ops:
            ops.event(0, "mission-started",
                             f"{cfg.scene.name}/{cfg.start}, {cfg.platform}, {cfg.condition}, "
                             f"{cfg.steps} steps")
        if ops:
            ops.describe_link(first)
        if resume:
            record.resumes.append({"step": first, "resume_s": time.perf_counter() - t_start})
            log.info("resumed at step %d, %.1f s after the start", first,
                     time.perf_counter() - t_start)
        t_step = time.perf_counter()
        for t in range(first, cfg.steps + 1):
            if STOP.is_set():  # Ctrl-C or SIGTERM: stop at the step boundary
                raise KeyboardInterrupt
            external = bool(transport.cfg.planner.command)
            if ops:
                t_boundary = time.perf_counter()
                ops.boundary(t)  # the link, and ground commands (they may pause or abort)
                if ops.abort:
                    state = "aborted"
                    break
                # A pause or a restart at the boundary is not the loop's step time.
                t_step += time.perf_counter() - t_boundary
                condition = transport.cfg.condition  # a ground command may have changed it
            if not record.conditions or record.conditions[-1][1] != condition:
                record.conditions.append((t, condition))
            cov = record.coverage[-1] if record.coverage else 0.0
            transport.tick(MissionStatus(t, cfg.steps, "running", condition, cov, collisions))
            if t > 0:
                path = transport.receive("path", t - 1)
                # The built-in planner always says what it rejected; a planner of the user's own
                # (--planner.command) need not, and is not waited for. (Which planner planned
                # step t-1 is read before this boundary, which may swap it.)
                rejected = (transport.poll if external else transport.receive)("rejected", t - 1)
                traverse = (transport.poll if external else transport.receive)("traverse", t - 1)
                if traverse is not None:  # (the record keeps no point indices)
                    record.traverse.append(dataclasses.replace(
                        traverse, gain_points=np.zeros(0, dtype=np.uint32)))
                record.paths.append(path)
                report = transport.receive("execution", t - 1)
                collisions += int(report.collided)
                record.executions.append(report)
                predicted = xyz(transport.receive("predicted", t - 1))
                predicted = predicted[in_region(predicted, cfg.scene.bounds_m)]
                planner_map = transport.receive("planner_map", t - 1)
                # What the gate passed on to the gain (under gated-split the collision channel
                # keeps more; every other condition passes the same to both).
                attracting = planner_map.serving(Channel.GAIN).points
                kept = attracting[attracting["source"] == Source.PREDICTED]
                record.predicted_points.append(len(predicted))
                record.planner_predicted.append(len(kept))
                # The map carries no count of what the gate withheld; under the gate, what it
                # withheld is what it did not pass on (in the scored region, where it works).
                withholds = get_condition(condition).withholds
                record.suppressed.append(len(predicted) - len(kept) if withholds else 0)
                if withholds:
                    _, withheld_fp, predicted_fp = suppression_audit(
                        predicted, xyz(kept), judge.reference, cfg.oracle_delta_m, judge.tree)
                    record.suppressed_fp.append(withheld_fp)
                    record.predicted_fp.append(predicted_fp)
                record.collision_class.append(collision_class(
                    report, planner_map, cfg, previous_base))
                contacts = np.array([e.contact for e in record.executions[:-1]
                                     if e.contact is not None]).reshape(-1, 3)
                decision = judge.decision(planner_map, path, rejected, previous_base, contacts,
                                          None if traverse is None else traverse.gain_points)
                record.fp_gain_share.append(decision.fp_gain_share)
                record.rejected_by_fp.append(decision.rejected_by_fp)
            surface = transport.receive("surface", t)
            base = transport.receive("base", t)
            if t > 0:
                record.step_wall_s.append(time.perf_counter() - t_step)
                t_step = time.perf_counter()
            record.base_xy.append((float(base.position[0]), float(base.position[1])))
            record.base_z.append(float(base.position[2]))
            previous_base = base
            surface_xyz = xyz(surface)
            record.coverage.append(evaluator.update(surface_xyz))
            if ops:
                ops.after_step(MissionStatus(t, cfg.steps, "running", condition,
                                             record.coverage[-1], collisions), base, surface)
            if on_step:
                on_step(t, record.coverage[-1])
            if t < cfg.steps and saver is not None:
                record.wall_s = wall_before + time.perf_counter() - t_start
                saver.save(LoopState(
                    t + 1, record, collisions, previous_base, condition,
                    transport.cfg, ops.snapshot() if ops else None,
                    transport.snapshot()))
        else:
            state = "done"
    finally:
        if surface_xyz is not None:  # the last step's, done or aborted: the top-down map
            record.surface_xyz = surface_xyz
        final = MissionStatus(len(record.coverage) - 1 if record.coverage else 0, cfg.steps,
                              "done" if state == "done" else "aborted", condition,
                              record.coverage[-1] if record.coverage else 0.0, collisions)
        try:
            transport.finish(final, failed=state == "failed")
        finally:
            if saver is not None:
                saver.close()
            if ops:
                try:
                    if state != "failed":
                        record.link = ops.finish(final)
                finally:
                    ops.close()
    record.state = state
    for timing in sorted(transport.timings(), key=lambda t: (t.module, t.step)):
        record.add_stage(timing.module, timing.compute_s)
    record.restarts = transport.restarts()
    record.dropped_messages = transport.dropped()
    record.wall_s = wall_before + time.perf_counter() - t_start
    return record


def _open_taps(cfg: MissionConfig, out: Path, resumed: bool = False,
               writer: str = "thread") -> tuple[Taps, FlightRecorder | None]:
    """The taps of a mission (:mod:`rovergate.taps`): the flight recorder unless
    ``--no-record``, the live view with ``--viz``, the ROS 2 graph with ``--ros2``. Returns
    the taps and the recorder (None when not recording)."""
    from rovergate.taps import Taps
    taps = Taps([])
    recorder = None
    try:
        if cfg.record:
            from ecosystem.recorder import FlightRecorder, fresh_bag_dir
            bag = fresh_bag_dir(out, resumed)
            recorder = FlightRecorder(bag, cfg.session.namespace, cfg.record_compression, writer)
            taps.taps.append(recorder)
            log.info("recording every topic into %s (a rosbag2 bag; `--no-record` turns it off)",
                     bag)
        if cfg.viz:
            from ecosystem.live_view import LiveView
            from rover_sim.catalog import load_scene
            taps.taps.append(LiveView(cfg.viz_host, cfg.viz_port, cfg.session.namespace,
                                      load_scene(cfg.scene), hazcam=cfg.hazcam))
        if cfg.ros2:
            from ecosystem.ros2 import Ros2Bridge
            taps.taps.append(Ros2Bridge(cfg.ros2_router, cfg.ros2_domain,
                                        cfg.session.namespace))
    except BaseException:
        taps.close()
        raise
    return taps, recorder


def _recording(recorder: FlightRecorder | None) -> dict:
    """What the flight recorder wrote (metrics.json's ``recording``)."""
    return dataclasses.asdict(recorder.stats) if recorder is not None else {}


def run_in_process(cfg: MissionConfig, on_step: OnStep | None = None) -> MissionRecord:
    """The mission with every module in this process, without Zenoh (the study's runs)."""
    # The bag is written by a process of its own: the loop needs this process's Python lock.
    taps, recorder = _open_taps(cfg, Path(cfg.out), writer="process")
    try:
        record = run_mission(cfg, InProcessTransport(cfg, taps), on_step)
    finally:
        taps.close()
    record.recording = _recording(recorder)
    return record


def run_processes(cfg: MissionConfig, on_step: OnStep | None = None,
                  resume: LoopState | None = None,
                  on_link: Callable[[], None] | None = None) -> MissionRecord:
    """The mission as a process set over Zenoh, with the ground link when it is enabled. Its
    state is checkpointed in ``cfg.out`` after every step (removed when the mission ends,
    kept when it fails or its manager is killed); ``resume`` carries on from such a state.
    ``on_link`` is called once the ground link's endpoint is up."""
    from mission.link.operations import Operations
    from mission.runtime.process_set import ProcessSetTransport
    out = Path(cfg.out)
    taps, recorder = _open_taps(cfg, out, resumed=resume is not None)
    try:
        transport = ProcessSetTransport(cfg, out, {**resume.transport, "step": resume.step}
                                        if resume else None, taps)
        def factory() -> Operations:
            ops = Operations(transport)
            if on_link is not None:
                try:
                    on_link()
                except BaseException:
                    ops.close()  # the link's session and ground.json
                    raise
            return ops
        record = run_mission(cfg, transport, on_step,
                             factory if cfg.contact.enabled else None, checkpoint=out,
                             resume=resume)
    finally:
        taps.close()
    record.recording = _recording(recorder)
    remove_checkpoint(out)
    return record
