"""The mission as a process set: launch the modules, run the clock over Zenoh, shut down.

The hub is the mission process itself. It opens a peer session that listens on a free loopback
port (plus any ``--listen`` endpoints, for subscribers on other machines), declares the
mission's liveliness token, starts each module as its own OS process connected to it, waits
for every module's liveliness token (never a fixed sleep), then ticks the mission clock on
``<ns>/mission/status``: step t starts when the simulator receives the tick of step t and the
path of step t-1. Coverage is evaluated here from ``<ns>/map/surface`` and the true surface
samples that the simulator serves on ``<ns>/truth/surface_samples``.

Health: the hub watches every module's process and liveliness token. When a module dies
(or its token vanishes), the loop cannot go on without it, so the rover holds still: the
simulator executes only the path of the step before, and none comes. The hub restarts the
module with ``--resume-step`` (at most ``max_restarts`` times each); the module rebuilds its
state from the hub's journal of past inputs (:mod:`mission.journal`) and the loop resumes at
the same step, with the same numbers as if nothing had happened.
"""

from __future__ import annotations

import dataclasses
import logging
import queue
import shlex
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import zenoh
from scipy.spatial import cKDTree

from mapper.integrate import voxel_first_points
from mission.coverage import CoverageEvaluator
from mission.journal import Journal
from mission.metrics import suppression_audit
from mission.record import MissionRecord
from rovergate.config import MissionConfig, save_config
from rovergate.keys import MODULES, PROGRESS_TOPIC, Keys
from rovergate.messages import MessageError, encode
from rovergate.node import STOP, cdr_encoding, check_and_decode
from rovergate.session import free_loopback_port, open_session
from rovergate.types import MissionStatus, Source, xyz

log = logging.getLogger("rovergate.mission")

#: Which module reports each stage on the timing topic.
STAGE_MODULE = {"render": "sim", "execute": "sim", "integrate": "mapper", "gate": "gate",
                "plan": "planner"}


class MissionFailed(RuntimeError):
    """A module died more often than it may be restarted, or something the mission waited for
    did not come in time."""


@dataclasses.dataclass
class RestartEvent:
    """A module that died during the mission, and how the loop recovered."""

    module: str
    step: int
    """The step the restarted module resumed at (the last one it had finished, redone)."""
    reason: str
    died_s: float
    """When the death was noticed, seconds since the mission started."""
    ready_s: float | None = None
    """When the restarted module's liveliness token came back."""
    resumed_s: float | None = None
    """When the loop resumed: the restarted module's first output came in."""

    def as_dict(self) -> dict[str, Any]:
        d = dataclasses.asdict(self)
        d["death_to_ready_s"] = (self.ready_s - self.died_s) if self.ready_s else None
        d["death_to_resume_s"] = (self.resumed_s - self.died_s) if self.resumed_s else None
        return d


class Hub:
    """The mission's Zenoh session, its module processes, and the step-indexed inbox."""

    WATCHED = ("surface", "path", "execution", "timing", "base_pose", "predicted",
               "planner_map")

    def __init__(self, cfg: MissionConfig, out: Path) -> None:
        self.cfg = cfg
        self.out = out
        self.keys = Keys(cfg.session.namespace)
        self.endpoint = f"tcp/127.0.0.1:{free_loopback_port()}"
        hub_cfg = dataclasses.replace(cfg.session, mode="peer", wait_for_peers=0,
                                      listen=(self.endpoint, *cfg.session.listen))
        self.session = open_session(hub_cfg)
        self.inbox: dict[str, dict[int, Any]] = {t: {} for t in self.WATCHED}
        self.timings: queue.Queue = queue.Queue()
        self.dropped = 0
        self._cv = threading.Condition()
        self.journal = Journal()
        self.last_seen: dict[str, int] = {}
        self.t0 = time.monotonic()
        self.events: list[RestartEvent] = []
        self._resuming: dict[str, RestartEvent] = {}
        self._subs = [self.session.declare_subscriber(self.keys.key(t), self._on_sample(t))
                      for t in set(self.WATCHED) | (self.journal.topics - {"status"})]
        self._journal_qs = [self.session.declare_queryable(self.keys.journal(t),
                                                           self._on_journal_query(t))
                            for t in self.journal.topics]
        self._alive: set[str] = set()
        self._ever_alive: set[str] = set()
        self._alive_sub = self.session.liveliness().declare_subscriber(
            self.keys.alive_all, self._on_alive, history=True)
        self._status_pub = self.session.declare_publisher(
            self.keys.key("status"), encoding=cdr_encoding("status"),
            congestion_control=zenoh.CongestionControl.BLOCK)
        self._token = self.session.liveliness().declare_token(self.keys.alive("mission"))
        self.procs: dict[str, subprocess.Popen] = {}
        self._logs: list[Any] = []
        self._configs = 0

    def _on_sample(self, topic: str):
        def callback(sample: zenoh.Sample) -> None:
            try:
                step, value = check_and_decode(topic, sample)
            except MessageError as exc:
                self.dropped += 1
                log.warning("dropped a message on %s: %s", self.keys.key(topic), exc)
                return
            with self._cv:
                if topic in self.journal.topics:
                    self.journal.add(topic, step, sample.payload.to_bytes())
                self.last_seen[topic] = max(step, self.last_seen.get(topic, -1))
                if topic == "timing":
                    self.timings.put(value)
                elif topic in self.inbox:
                    self.inbox[topic][step] = value
                for name, event in list(self._resuming.items()):
                    if topic == PROGRESS_TOPIC[name] and step >= event.step:
                        event.resumed_s = self.elapsed()
                        log.info("%s is back: the loop resumed at step %d, %.2f s after it "
                                 "died", name, step, event.resumed_s - event.died_s)
                        del self._resuming[name]
                self._cv.notify_all()
        return callback

    def _on_journal_query(self, topic: str):
        key = self.keys.journal(topic)
        encoding = cdr_encoding(topic)

        def on_query(query: zenoh.Query) -> None:
            try:
                first = int(query.parameters.get("from", "0"))
                last = int(query.parameters.get("to", str(first)))
            except ValueError:
                log.warning("journal query %s has non-integer from/to; ignored", query.selector)
                return
            with self._cv:
                entries = list(self.journal.range(topic, first, last))
            for entry in entries:
                query.reply(key, entry.payload, encoding=encoding)
        return on_query

    def elapsed(self) -> float:
        return time.monotonic() - self.t0

    def _on_alive(self, sample: zenoh.Sample) -> None:
        name = str(sample.key_expr).rsplit("/", 1)[-1]
        with self._cv:
            if sample.kind == zenoh.SampleKind.PUT:
                self._alive.add(name)
                self._ever_alive.add(name)
                event = self._resuming.get(name)
                if event is not None and event.ready_s is None:
                    event.ready_s = self.elapsed()
            else:
                self._alive.discard(name)
            self._cv.notify_all()

    # --- processes ------------------------------------------------------------------------

    def launch(self, config_path: Path) -> None:
        """Start every module as its own OS process, logging to ``out/logs/<module>.log``."""
        self.config_path = config_path
        (self.out / "logs").mkdir(parents=True, exist_ok=True)
        for name in MODULES:
            self._spawn(name)

    def _spawn(self, name: str, resume_step: int | None = None) -> None:
        if name == "planner" and self.cfg.planner.command:
            # A planner of the user's own: it gets the endpoint and the namespace.
            cmd = [*shlex.split(self.cfg.planner.command), "--connect", self.endpoint,
                   "--namespace", self.cfg.session.namespace]
        else:
            cmd = [sys.executable, "-m", "rovergate.cli", name, "--config",
                   str(self.config_path), "--mode", "peer", "--connect", self.endpoint,
                   "--listen", "tcp/127.0.0.1:0", "--namespace", self.cfg.session.namespace,
                   "--wait-for-peers", str(len(MODULES))]
            if resume_step is not None:
                cmd += ["--resume-step", str(resume_step)]
        # A restarted module appends to the log of the one that died.
        f = open(self.out / "logs" / f"{name}.log",  # noqa: SIM115 -- closed in shutdown()
                 "w" if resume_step is None else "a")
        self._logs.append(f)
        try:
            self.procs[name] = subprocess.Popen(cmd, stdout=f, stderr=subprocess.STDOUT,
                                                stdin=subprocess.DEVNULL)
        except OSError as exc:
            raise MissionFailed(f"could not start {name} ({' '.join(cmd)}): {exc}") from None
        log.info("started %s (pid %d)%s", name, self.procs[name].pid,
                 "" if resume_step is None else f", resuming at step {resume_step}")

    def check_health(self) -> bool:
        """:meth:`check_processes` from outside a wait."""
        with self._cv:
            return self.check_processes()

    def check_processes(self) -> bool:
        """Restart every module that died; True when one was restarted."""
        restarted = False
        for name, p in list(self.procs.items()):
            code = p.poll()
            if code is not None:
                self._restart(name, f"exited with code {code}")
                restarted = True
            elif name in self._ever_alive and name not in self._alive \
                    and name not in self._resuming:
                # Alive as a process but gone from the network (hung, or cut off): the loop
                # cannot reach it, so it is replaced.
                self._restart(name, "its liveliness token vanished")
                restarted = True
        return restarted

    def reconfigure(self, cfg: MissionConfig, modules: list[str], step: int) -> None:
        """Restart ``modules`` with ``cfg`` at the boundary before ``step`` (every module is
        then waiting for step ``step``'s inputs); they rebuild their state from the journal."""
        self.cfg = cfg
        self._configs += 1
        self.config_path = self.out / f"config.{self._configs}.json"
        save_config(cfg, self.config_path)
        with self._cv:
            for name in modules:
                self.procs[name].terminate()
            for name in modules:
                try:
                    self.procs[name].wait(30)
                except subprocess.TimeoutExpired:
                    self.procs[name].kill()
                    self.procs[name].wait()
            for name in modules:
                self._respawn(name, step)
        self._wait(lambda: self._alive.issuperset(modules),
                   "the liveliness tokens of the restarted " + ", ".join(modules),
                   self.cfg.ready_timeout_s)

    def _restart(self, name: str, reason: str) -> None:
        died = self.elapsed()
        p = self.procs[name]
        if p.poll() is None:
            p.kill()
            p.wait()
        restarts = 1 + sum(e.module == name for e in self.events)
        if restarts > self.cfg.max_restarts:
            raise MissionFailed(
                f"module {name!r} {reason} during the mission, after {restarts - 1} "
                f"restarts (--max-restarts {self.cfg.max_restarts}); its log is "
                f"{self.out / 'logs' / (name + '.log')}:\n{_tail(self.out, name)}")
        # Resume at the last step whose output the mission has seen, redone: whatever of it
        # reached others again is a duplicate of the same bytes, which they ignore.
        step = max(0, self.last_seen.get(PROGRESS_TOPIC[name], 0))
        log.warning("module %s %s at step %d; the rover holds still while it restarts "
                    "(restart %d of at most %d)", name, reason, step, restarts,
                    self.cfg.max_restarts)
        event = RestartEvent(name, step, reason, died)
        self.events.append(event)
        self._resuming[name] = event
        self._respawn(name, step)

    def _respawn(self, name: str, step: int) -> None:
        """Start ``name`` again (its old process has exited), resuming at ``step``."""
        self._alive.discard(name)
        self._ever_alive.discard(name)
        self._spawn(name, resume_step=step)

    def _wait(self, ready, what: str, timeout_s: float, restart: bool = True) -> None:
        deadline = time.monotonic() + timeout_s
        with self._cv:
            while not ready():
                left = deadline - time.monotonic()
                if left <= 0:
                    raise MissionFailed(f"timed out after {timeout_s:.0f} s waiting for {what}")
                self._cv.wait(min(left, 0.05))
                if STOP.is_set():
                    raise KeyboardInterrupt
                if restart:
                    if self.check_processes():  # a restart gets the full time again
                        deadline = time.monotonic() + self.cfg.ready_timeout_s + timeout_s
                else:
                    self._fail_on_exit()

    def _fail_on_exit(self) -> None:
        for name, p in self.procs.items():
            code = p.poll()
            if code is not None:
                raise MissionFailed(
                    f"module {name!r} exited with code {code} before the mission started; its "
                    f"log is {self.out / 'logs' / (name + '.log')}:\n{_tail(self.out, name)}")

    def wait_ready(self) -> None:
        self._wait(lambda: self._alive.issuperset(MODULES),
                   "the liveliness tokens of " + ", ".join(
                       f"{self.keys.alive(m)}" for m in MODULES if m not in self._alive),
                   self.cfg.ready_timeout_s, restart=False)

    def wait_message(self, topic: str, step: int) -> Any:
        self._wait(lambda: step in self.inbox[topic],
                   f"{self.keys.key(topic)} of step {step}", self.cfg.step_timeout_s)
        with self._cv:
            return self.inbox[topic].pop(step)

    def query_truth_surface(self) -> Any:
        key = self.keys.key("truth_surface")
        deadline = time.monotonic() + self.cfg.ready_timeout_s
        while time.monotonic() < deadline:
            self._fail_on_exit()
            for reply in self.session.get(key, timeout=30.0, attachment="mission"):
                if reply.ok is not None:
                    return xyz(check_and_decode("truth_surface", reply.ok)[1])
            time.sleep(0.2)
        raise MissionFailed(f"timed out waiting for an answer on {key}")

    def publish_status(self, status: MissionStatus) -> None:
        payload = encode("status", status)
        if status.state == "running":  # the ticks; a restarted simulator replays them
            with self._cv:
                self.journal.add("status", status.step, payload)
        self._status_pub.put(payload)

    def shutdown(self, timeout_s: float = 30.0) -> dict[str, int | None]:
        """Wait for the modules to exit (they stop on the final status), then close."""
        codes: dict[str, int | None] = {}
        deadline = time.monotonic() + timeout_s
        for name, p in self.procs.items():
            try:
                codes[name] = p.wait(max(0.1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                log.error("%s did not exit within %.0f s; terminating it", name, timeout_s)
                p.terminate()
                try:
                    codes[name] = p.wait(5)
                except subprocess.TimeoutExpired:
                    p.kill()
                    codes[name] = p.wait()
        for f in self._logs:
            f.close()
        self._token.undeclare()
        for s in self._subs:
            s.undeclare()
        for q in self._journal_qs:
            q.undeclare()
        self._alive_sub.undeclare()
        self.session.close()
        return codes

    def kill_all(self) -> None:
        for p in self.procs.values():
            if p.poll() is None:
                p.terminate()
        for p in self.procs.values():
            try:
                p.wait(10)
            except subprocess.TimeoutExpired:
                p.kill()


def _tail(out: Path, name: str, lines: int = 15) -> str:
    path = out / "logs" / f"{name}.log"
    try:
        text = path.read_text(errors="replace").splitlines()
    except OSError:
        return ""
    return "\n".join("    " + line for line in text[-lines:])


def run_processes(cfg: MissionConfig, on_step=None) -> MissionRecord:
    """Run the mission as a process set over Zenoh; raises MissionFailed on a fault."""
    from mission.operations import Operations
    out = Path(cfg.out)
    record = MissionRecord(mode="processes")
    t_start = time.perf_counter()
    hub = Hub(cfg, out)
    config_path = out / "config.json"
    save_config(cfg, config_path)
    state = "failed"
    collisions = 0
    ops = None
    try:
        ops = Operations(hub) if cfg.contact.enabled else None
        hub.launch(config_path)
        hub.wait_ready()
        log.info("all modules ready: %s", ", ".join(MODULES))
        truth_surface = hub.query_truth_surface()
        evaluator = CoverageEvaluator(truth_surface, cfg.eval.tau_frac * cfg.scene.d_scene_m)
        # Evaluation only: the reference occupancy O* (as the simulator derives it) to audit
        # what the gate withheld.
        audit_ref = audit_tree = None  # built when the condition is (or becomes) gated
        delta_m = cfg.gate.oracle_delta_frac * cfg.scene.d_scene_m
        if ops:
            ops.bridge.event(0, "mission-started",
                             f"{cfg.scene.name}/{cfg.start}, {cfg.platform}, {cfg.condition}, "
                             f"{cfg.steps} steps")
        t_step = time.perf_counter()
        for t in range(cfg.steps + 1):
            if ops:
                t_boundary = time.perf_counter()
                ops.boundary(t)  # the link, and ground commands (they may pause or abort)
                if ops.abort:
                    state = "aborted"
                    break
                # A pause or a restart at the boundary is not the loop's step time.
                t_step += time.perf_counter() - t_boundary
            condition = hub.cfg.condition  # a ground command may have changed it
            cov = record.coverage[-1] if record.coverage else 0.0
            hub.publish_status(MissionStatus(t, cfg.steps, "running", condition, cov,
                                             collisions))
            if t > 0:
                record.paths.append(hub.wait_message("path", t - 1))
                report = hub.wait_message("execution", t - 1)
                collisions += int(report.collided)
                record.executions.append(report)
            if t > 0:
                predicted = hub.wait_message("predicted", t - 1)
                planner_map = hub.wait_message("planner_map", t - 1)
                kept_points = planner_map.points[planner_map.points["source"] == Source.PREDICTED]
                kept = len(kept_points)
                record.predicted_points.append(len(predicted))
                record.planner_predicted.append(kept)
                if condition == "gated":
                    if audit_ref is None:
                        audit_ref = voxel_first_points(truth_surface, cfg.mapper.voxel_m)
                        audit_tree = cKDTree(audit_ref)
                    record.suppressed_fp.append(suppression_audit(
                        xyz(predicted), xyz(kept_points), audit_ref, delta_m, audit_tree)[1])
                # The map message has no count of what the gate withheld; under the gate,
                # what it withheld is what it did not pass on.
                record.suppressed.append(len(predicted) - kept if condition == "gated" else 0)
            surface = hub.wait_message("surface", t)
            base = hub.wait_message("base_pose", t)
            if t > 0:
                record.step_wall_s.append(time.perf_counter() - t_step)
                t_step = time.perf_counter()
            record.base_xy.append((float(base.position[0]), float(base.position[1])))
            record.coverage.append(evaluator.update(xyz(surface)))
            if ops:
                ops.after_step(MissionStatus(t, cfg.steps, "running", condition,
                                             record.coverage[-1], collisions), base, surface)
            if on_step:
                on_step(t, record.coverage[-1])
            if t == cfg.steps:
                record.surface_xyz = xyz(surface)
        else:
            state = "done"
    finally:
        final = MissionStatus(len(record.coverage) - 1 if record.coverage else 0, cfg.steps,
                              "done" if state == "done" else "aborted", hub.cfg.condition,
                              record.coverage[-1] if record.coverage else 0.0, collisions)
        try:
            hub.publish_status(final)
        finally:
            if state == "failed":
                hub.kill_all()
            codes = hub.shutdown()
            if ops:
                try:
                    if state != "failed":
                        record.link = ops.finish(final)
                finally:
                    ops.close()
    record.state = state
    dropped: dict[str, int] = {}
    timings = {}
    while not hub.timings.empty():
        timing = hub.timings.get()
        # A restarted module redoes its last step: keep one timing per stage and step.
        timings[(timing.module, timing.step)] = timing
    for (stage, _), timing in sorted(timings.items(), key=lambda kv: (kv[0][0], kv[0][1])):
        record.add_stage(stage, timing.compute_s)
        module = STAGE_MODULE.get(stage, stage)
        dropped[module] = max(dropped.get(module, 0), timing.dropped_total)
    record.restarts = [e.as_dict() for e in hub.events]
    record.dropped_messages = sum(dropped.values()) + hub.dropped
    record.wall_s = time.perf_counter() - t_start
    bad = {n: c for n, c in codes.items() if c != 0}
    if bad:
        raise MissionFailed("modules did not exit cleanly: " + ", ".join(
            f"{n} (exit code {c})" for n, c in bad.items()))
    return record


