"""The process set: every module its own OS process, the mission's messages over Zenoh.

:class:`ProcessSetTransport` implements :class:`mission.runtime.transport.Transport` by composing
parts that each do one job:

- a Zenoh peer session that listens on a Unix socket in a directory of its own, mode 0700
  (the modules connect to it as clients; nothing else listens on the rover network), plus
  any ``--listen`` endpoints for subscribers on other machines, which its access control
  makes read-only (:func:`rovergate.access.rover_network`); and the mission's liveliness
  token;
- the :class:`~mission.runtime.inbox.Inbox` its subscriptions fill (the mission's inputs, from the
  graph);
- the :class:`~mission.runtime.journal.JournalServer` (the past inputs a restarted module replays);
- the :class:`~mission.runtime.clock.MissionClock` (the ticks);
- the :class:`~mission.runtime.supervisor.ProcessSupervisor` (launch, watch, restart; no Zenoh).

Health: when a module dies (or its token vanishes), the loop cannot go on without it, so the
rover holds still: the simulator executes only the path of the step before, and none comes.
The module is restarted with ``--resume-step`` and rebuilds its state from the journal; the
loop resumes at the same step, with the same numbers as if nothing had happened.

It is also the :class:`mission.link.operations.MissionControl` that ground commands act through.
"""

from __future__ import annotations

import dataclasses
import logging
import shlex
import shutil
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

import zenoh

from mission.runtime.clock import MissionClock
from mission.runtime.inbox import Inbox
from mission.runtime.journal import JOURNAL, Journal, JournalServer
from mission.runtime.supervisor import ProcessSupervisor, RestartEvent
from rovergate.access import MODULE_PROTOCOL, rover_network
from rovergate.config import MissionConfig, save_config
from rovergate.errors import ConfigError, MissionFailed, ReconfigurationFailed
from rovergate.graph import LAUNCHED, MODULES, producer, stage_module
from rovergate.keys import Keys
from rovergate.messages import MessageError, prepare
from rovergate.module import STOP
from rovergate.node import Drops, ask_until_answered, decoding
from rovergate.session import open_session
from rovergate.streams import INCREMENTAL, StreamDecoder
from rovergate.taps import tapped_topics
from rovergate.types import MissionStatus, StepTiming

if TYPE_CHECKING:
    from rovergate.taps import Taps


@dataclasses.dataclass
class Reconfiguration:
    """A ground command's reconfiguration in force: the configuration before and after it,
    and the modules it restarted."""

    before: MissionConfig
    after: MissionConfig
    modules: list[str]


UNIX_PATH_MAX = 107
"""Longest path of a Unix socket (sun_path, less its terminating zero)."""

log = logging.getLogger("rovergate.mission")

#: The mission's inputs, by topic (the loop receives them by their names in the graph).
_MISSION_INPUTS = {i.topic: name for name, i in MODULES["mission"].inputs.items()}
#: Which module's last output each topic is (a restarted module is back once it comes).
_PROGRESS = {MODULES[m].progress: m for m in LAUNCHED}


def program_argv(command: str) -> list[str]:
    """A planner program's command line as argv; ``python`` or ``python3`` as its first word
    is the mission's own interpreter, so the program sees the mission's environment."""
    argv = shlex.split(command)
    if argv and argv[0] in ("python", "python3"):
        argv[0] = sys.executable
    return argv


class ProcessSetTransport:
    """The modules as processes over Zenoh (see the module docstring)."""

    mode = "processes"

    def __init__(self, cfg: MissionConfig, out: Path, resume: dict[str, Any] | None = None,
                 taps: Taps | None = None) -> None:
        """``resume``: :meth:`snapshot` of the transport of a mission whose manager died; the
        journal in ``out`` is loaded and every module resumes at the step before
        ``resume["step"]``. ``taps`` (the flight recorder, the live view) get every message
        of the rover's network, as it travelled, once it decoded."""
        self._cfg = cfg
        self.taps = taps
        self.out = out
        self._resume = resume
        out.mkdir(parents=True, exist_ok=True)
        self.keys = Keys(cfg.session.namespace)
        self._sockets = Path(tempfile.mkdtemp(prefix="rovergate-"))  # mode 0700
        try:
            self.endpoint, self.session = self._open_session(cfg, self._sockets)
        except BaseException:
            shutil.rmtree(self._sockets, ignore_errors=True)
            raise
        log.info("rover network: the modules connect to %s; %s", self.endpoint,
                 f"read-only for other machines on {', '.join(cfg.session.listen)}"
                 if cfg.session.listen else "no --listen endpoint for other machines")
        try:
            self._declare(cfg, out)
        except BaseException:
            self.session.close()
            shutil.rmtree(self._sockets, ignore_errors=True)
            raise

    @staticmethod
    def _open_session(cfg: MissionConfig, sockets: Path) -> tuple[str, zenoh.Session]:
        """The mission's peer session on a Unix socket in ``sockets`` (the modules connect to
        it), plus any ``--listen`` endpoints, under the rover network's access control."""
        endpoint = f"{MODULE_PROTOCOL}/{sockets / 'mission.sock'}"
        if len(str(sockets / "mission.sock")) > UNIX_PATH_MAX:
            raise ConfigError(f"the temporary directory {sockets.parent} has too long a path "
                              f"for a Unix socket (at most {UNIX_PATH_MAX} bytes); set TMPDIR "
                              "to a shorter one, e.g. TMPDIR=/tmp")
        for given in cfg.session.listen:
            if given.split("/", 1)[0] == MODULE_PROTOCOL:
                raise ConfigError(f"--listen {given}: {MODULE_PROTOCOL} is the modules' own "
                                  "transport, with full rights; other machines subscribe over "
                                  "tcp/ADDRESS:PORT (read-only)")
        session_cfg = dataclasses.replace(cfg.session, mode="peer", wait_for_peers=0,
                                          listen=(endpoint, *cfg.session.listen))
        return endpoint, open_session(session_cfg, rover_network(cfg.session.namespace))

    def _declare(self, cfg: MissionConfig, out: Path) -> None:
        journal_file = out / JOURNAL
        if self._resume is None:
            journal_file.unlink(missing_ok=True)  # another mission's, in the same --out
            for extra in ("-wal", "-shm"):
                journal_file.with_name(JOURNAL + extra).unlink(missing_ok=True)
        self.journal = Journal(path=journal_file)
        prepare({*_MISSION_INPUTS, *self.journal.topics, *MODULES["mission"].asks, "timing"})
        watched = set(_MISSION_INPUTS) | {"timing"}
        self.inbox = Inbox(watched - {"timing"})
        self._timings: dict[tuple[str, int], StepTiming] = {}
        self._drops = Drops(log)
        self._restarts_before: list[dict[str, Any]] = []
        self._undoable: list[Reconfiguration] = []
        """Ground reconfigurations in force, oldest first (what a rollback undoes)."""
        self.rollbacks: list[tuple[int, str]] = []
        """Reconfigurations undone because their modules kept dying or fell silent: the step
        and the reason."""
        cv = self.inbox.cv
        self.journal_server = JournalServer(self.session, self.keys, self.journal, cv)
        self.clock = MissionClock(self.session, self.keys, self.journal, cv, self.taps)
        self.config_path = out / "config.json"
        self._configs = 0
        if self._resume is not None:
            self._restore(self._resume)
        self.supervisor = ProcessSupervisor(LAUNCHED, self._command, out / "logs",
                                            cfg.max_restarts)
        # The taps (the flight recorder, the live view) get every topic, also those no module
        # reads (the hazard cameras' intrinsics, the traversability map).
        tapped = set(tapped_topics()) - {"status"} if self.taps else set()
        self._subs = [self.session.declare_subscriber(self.keys.key(t), self._on_sample(t))
                      for t in watched | (self.journal.topics - {"status"}) | tapped]
        self._alive_sub = self.session.liveliness().declare_subscriber(
            self.keys.alive_all, self._on_alive, history=True)
        self._token = self.session.liveliness().declare_token(self.keys.alive("mission"))

    # --- MissionControl -------------------------------------------------------------------

    @property
    def cfg(self) -> MissionConfig:
        """The configuration as it stands (ground commands change it)."""
        return self._cfg

    @property
    def restart_events(self) -> list[RestartEvent]:
        return self.supervisor.events

    def publish_status(self, status: MissionStatus) -> None:
        self.clock.publish(status)

    def check_health(self) -> bool:
        """Restart every module that died; True when one was."""
        with self.inbox.cv:
            return self._check_processes()

    def reconfigure(self, cfg: MissionConfig, modules: list[str], step: int) -> None:
        """Restart ``modules`` with ``cfg`` at the boundary before ``step`` (every module is
        then waiting for step ``step``'s inputs); they rebuild their state from the journal.
        If one of them exits or shows no liveliness token within ``ready_timeout_s``, they
        are restarted with the previous configuration and :class:`ReconfigurationFailed`
        says why: a swap whose module does not come up costs the mission a few seconds. One
        that comes up and dies later is restarted like any crashed module; once it has died
        more than ``max_restarts`` times, the modules of the reconfiguration are restarted on
        the previous configuration instead of the mission failing (:attr:`rollbacks`)."""
        previous = self._cfg
        if step > 0:
            # The boundary comes once the simulator's step - 1 is in; the modules downstream
            # may still be at work on it. Stopping one then would lose its output of step - 1,
            # which nobody would send again (the new one starts at ``step``).
            progress = [MODULES[m].progress for m in modules]
            self._wait(lambda: all(self.inbox.last_seen.get(t, -1) >= step - 1
                                   for t in progress),
                       f"the outputs of step {step - 1} of {', '.join(modules)}",
                       self._cfg.step_timeout_s)
        try:
            self._restart_with(cfg, modules, step, new=True)
            self._undoable.append(Reconfiguration(previous, cfg, list(modules)))
        except MissionFailed as exc:
            why = str(exc).splitlines()[0]
            log.warning("%s did not come up with the new configuration (%s); restarting with "
                        "the previous one", ", ".join(modules), why)
            self._restart_with(previous, modules, step, new=False)
            raise ReconfigurationFailed(
                f"{', '.join(modules)} did not come up with the new configuration ({why}); "
                "the previous configuration runs on") from None

    def _restart_with(self, cfg: MissionConfig, modules: list[str], step: int,
                      new: bool) -> None:
        """Restart ``modules`` with ``cfg`` and wait for their tokens; with a ``new``
        configuration, one of them exiting raises :class:`MissionFailed` at once (a module
        that cannot run with it is not restarted on it)."""
        self._cfg = cfg
        self._configs += 1
        self.config_path = self.out / f"config.{self._configs}.json"
        save_config(cfg, self.config_path)
        with self.inbox.cv:
            self.supervisor.replace(modules, step)
        self._wait(lambda: self.supervisor.alive.issuperset(modules),
                   "the liveliness tokens of the restarted " + ", ".join(modules),
                   cfg.ready_timeout_s, exits_fail=modules if new else ())

    # --- callbacks (Zenoh's threads) ------------------------------------------------------

    def _on_sample(self, topic: str) -> Callable[[zenoh.Sample], None]:
        journalled = topic in self.journal.topics

        # Decoded whole even where only the step is needed (the camera's depth, intrinsics
        # and pose, which the mission only journals): what the journal keeps is replayed into
        # restarted modules, so it must be valid.
        decoder = StreamDecoder(topic) if topic in INCREMENTAL else None

        def callback(step: int, value: Any, sample: zenoh.Sample) -> None:
            payload = sample.payload.to_bytes()
            if self.taps:
                self.taps.put(topic, payload)
            with self.inbox.cv:
                if journalled:
                    self.journal.add(topic, step, payload,
                                     keyframe=decoder is None or value.keyframe)
                if topic == "timing":
                    # A restarted module redoes its last step: one timing per stage and step.
                    self._timings[(value.module, value.step)] = value
                if decoder is None:
                    self.inbox.put(topic, step, value)
                else:  # an incremental map: whole again, in step order (rovergate.streams)
                    try:
                        for whole_step, whole in decoder.offer(value):
                            self.inbox.put(topic, whole_step, whole)
                    except MessageError as exc:
                        self._drops.drop(self.keys.key(topic), exc)
                if topic in _PROGRESS:
                    self.supervisor.mark_progress(_PROGRESS[topic], step)
        return decoding(topic, self.keys.key(topic), self._drops, callback)

    def _on_alive(self, sample: zenoh.Sample) -> None:
        name = str(sample.key_expr).rsplit("/", 1)[-1]
        with self.inbox.cv:
            self.supervisor.mark_alive(name, sample.kind == zenoh.SampleKind.PUT)
            self.inbox.cv.notify_all()

    # --- processes ------------------------------------------------------------------------

    def _command(self, name: str, resume_step: int | None) -> list[str]:
        cfg = self._cfg
        if name == "planner" and cfg.planner.command:
            # A planner of the user's own: it gets the endpoint and the namespace.
            return [*program_argv(cfg.planner.command), "--connect", self.endpoint,
                    "--namespace", cfg.session.namespace]
        # A client of the mission's session, listening on nothing: every message between
        # modules passes the one session whose access control governs the network.
        cmd = [sys.executable, "-m", "mission.runtime.modules", name,
               "--config", str(self.config_path), "--mode", "client",
               "--connect", self.endpoint, "--listen",  # (none)
               "--namespace", cfg.session.namespace, "--wait-for-peers", "1"]
        if resume_step is not None:
            cmd += ["--resume-step", str(resume_step)]
        return cmd

    def _check_processes(self) -> bool:
        dead = self.supervisor.dead()
        for name, reason in dead:
            # Resume at the last step whose output the mission has seen, redone: whatever of
            # it reached others again is a duplicate of the same bytes, which they ignore.
            step = max(0, self.inbox.last_seen.get(MODULES[name].progress, 0))
            try:
                self.supervisor.restart(name, reason, step)
            except MissionFailed:
                if not self._roll_back(name, f"{reason} more than --max-restarts "
                                             f"{self._cfg.max_restarts} times"):
                    raise
        return bool(dead)

    def _roll_back(self, name: str, why: str) -> bool:
        """``name`` keeps failing (``why``) since the latest ground reconfiguration that
        restarted it: undo that one. The settings it changed go back to what they were
        (others, changed by later commands, stay), and every module it restarted restarts
        again, each redoing the last step the mission saw of it. False when no
        reconfiguration restarted ``name``: the failure is the mission's own."""
        undo = next((r for r in reversed(self._undoable) if name in r.modules), None)
        if undo is None:
            return False
        self._undoable.remove(undo)
        cfg = self._cfg
        for f in dataclasses.fields(cfg):
            before, after = getattr(undo.before, f.name), getattr(undo.after, f.name)
            if before != after and getattr(cfg, f.name) == after:
                cfg = dataclasses.replace(cfg, **{f.name: before})
        step = max(0, self.inbox.last_seen.get(MODULES[name].progress, 0))
        detail = (f"{name} {why} with the new configuration; {', '.join(undo.modules)} "
                  "restarted with the previous one")
        log.warning("reconfiguration rolled back: %s", detail)
        self.rollbacks.append((step, detail))
        self._cfg = cfg
        self._configs += 1
        self.config_path = self.out / f"config.{self._configs}.json"
        save_config(cfg, self.config_path)
        for m in undo.modules:
            self.supervisor.restart(m, f"rolled back: {why}" if m == name else "rolled back",
                                    max(0, self.inbox.last_seen.get(MODULES[m].progress, 0)),
                                    limit=False)
        return True

    def _wait(self, ready: Callable[[], bool], what: str, timeout_s: float,
              restart: bool = True, exits_fail: tuple[str, ...] | list[str] = ()) -> None:
        deadline = time.monotonic() + timeout_s
        with self.inbox.cv:
            while not ready():
                left = deadline - time.monotonic()
                if left <= 0:
                    raise MissionFailed(f"timed out after {timeout_s:.0f} s waiting for {what}")
                # Woken by every message and token; the timeout only bounds how late a dead
                # process (which sends nothing) is noticed.
                self.inbox.cv.wait(min(left, 0.05))
                if STOP.is_set():
                    raise KeyboardInterrupt
                for name in exits_fail:
                    self.supervisor.fail_on_exit(
                        "while coming up with the new configuration", only=name)
                if restart:
                    if self._check_processes():  # a restart gets the full time again
                        deadline = time.monotonic() + self._cfg.ready_timeout_s + timeout_s
                else:
                    self.supervisor.fail_on_exit()

    # --- Transport ------------------------------------------------------------------------

    def start(self) -> None:
        save_config(self._cfg, self.config_path)
        if self._resume is None:
            self.supervisor.start_all()
        else:
            # Every module redoes the last step the loop had finished, from the journal: the
            # one step whose outputs the mission may not have had all of when it died.
            step = max(0, self._resume["step"] - 1)
            self.supervisor.start_all(resume_step=step)
        self._wait(lambda: self.supervisor.all_alive,
                   "the liveliness tokens of " + ", ".join(
                       self.keys.alive(m) for m in LAUNCHED if m not in self.supervisor.alive),
                   self._cfg.ready_timeout_s, restart=False)
        log.info("all modules ready: %s", ", ".join(LAUNCHED))

    def ask(self, topic: str) -> Any:
        key = self.keys.key(topic)
        try:
            return ask_until_answered(self.session, key, topic, "mission",
                                      self._cfg.ready_timeout_s, log,
                                      before_each=self.supervisor.fail_on_exit)
        except TimeoutError:
            raise MissionFailed(f"timed out waiting for an answer on {key}") from None

    def tick(self, status: MissionStatus) -> None:
        self.clock.publish(status)

    def receive(self, name: str, step: int) -> Any:
        topic = MODULES["mission"].inputs[name].topic
        what = f"{self.keys.key(topic)} of step {step}"
        while True:
            try:
                self._wait(lambda: self.inbox.has(topic, step), what, self._cfg.step_timeout_s)
                break
            except MissionFailed:
                # A module the ground reconfigured that came up and then fell silent: undo
                # that reconfiguration and wait again; any other silence ends the mission.
                with self.inbox.cv:
                    if not self._roll_back(producer(topic), f"sent no {what} within "
                                           f"{self._cfg.step_timeout_s:.0f} s"):
                        raise
        with self.inbox.cv:
            return self.inbox.pop(topic, step)

    def poll(self, name: str, step: int) -> Any | None:
        topic = MODULES["mission"].inputs[name].topic
        with self.inbox.cv:
            return self.inbox.pop(topic, step) if self.inbox.has(topic, step) else None

    def timings(self) -> list[StepTiming]:
        with self.inbox.cv:
            return list(self._timings.values())

    def dropped(self) -> int:
        """The mission's own drops, plus each module's: a module reports its running count
        with every stage timing, so each module counts once, with its largest count."""
        stages = stage_module()
        by_module: dict[str, int] = {}
        with self.inbox.cv:
            for t in self._timings.values():
                module = stages.get(t.module, t.module)  # StepTiming.module holds the stage
                by_module[module] = max(by_module.get(module, 0), t.dropped_total)
            return self._drops.count + sum(by_module.values())

    def restarts(self) -> list[dict[str, Any]]:
        return self._restarts_before + [e.as_dict() for e in self.supervisor.events]

    # --- the mission manager's checkpoint (mission.runtime.checkpoint) ----------------------------

    def snapshot(self) -> dict[str, Any]:
        """What a resumed manager's transport needs: counts and timings so far, the ground
        reconfigurations that can still be undone, where the old one's socket was."""
        with self.inbox.cv:
            return {"timings": list(self._timings.values()), "dropped": self.dropped(),
                    "restarts": self.restarts(), "configs": self._configs,
                    "undoable": list(self._undoable), "sockets": str(self._sockets)}

    def _restore(self, snap: dict[str, Any]) -> None:
        # Each module counts its drops from 0 again: the counts so far become the mission's.
        self._timings = {(t.module, t.step): dataclasses.replace(t, dropped_total=0)
                         for t in snap["timings"]}
        self._drops.count = int(snap["dropped"])
        self._restarts_before = list(snap["restarts"])
        self._configs = int(snap["configs"])
        self._undoable = list(snap["undoable"])
        # The killed manager could not remove its socket's directory.
        old = Path(snap["sockets"])
        if old.name.startswith("rovergate-") and old.parent == self._sockets.parent:
            shutil.rmtree(old, ignore_errors=True)
        if self._configs:  # the configuration a ground command made, as the modules read it
            self.config_path = self.out / f"config.{self._configs}.json"

    def finish(self, final: MissionStatus, failed: bool) -> None:
        codes: dict[str, int | None] = {}
        try:
            self.clock.publish(final)
        finally:
            try:
                if failed:
                    self.supervisor.kill_all()
                codes = self.supervisor.shutdown()
            finally:
                # Whatever happened above, the session closes: a session left open keeps
                # the mission process alive.
                try:
                    self._token.undeclare()
                    for s in self._subs:
                        s.undeclare()
                    self.journal_server.close()
                    self.clock.close()
                    self._alive_sub.undeclare()
                finally:
                    self.session.close()
                    self.journal.close()
                    shutil.rmtree(self._sockets, ignore_errors=True)
        bad = {n: c for n, c in codes.items() if c != 0}
        if bad and not failed:
            raise MissionFailed("modules did not exit cleanly: " + ", ".join(
                f"{n} (exit code {c})" for n, c in bad.items()))

