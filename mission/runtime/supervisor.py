"""The process supervisor: launch the module processes, watch them, restart the ones that die.

It knows processes, their logs and the restart policy, and nothing of the network: the
transport tells it which modules' liveliness tokens are up (:meth:`mark_alive`), and gives it
the command line of each module (:data:`CommandFor`). It is not thread-safe; its one caller
(the Zenoh transport) holds its own lock around every call.
"""

from __future__ import annotations

import dataclasses
import logging
import subprocess
import time
from collections.abc import Callable
from pathlib import Path
from typing import IO, Any

from mission.runtime.launcher import LaunchedProcess, Launcher, module_args
from rovergate.errors import MissionFailed

log = logging.getLogger("rovergate.mission")

#: How long a module whose liveliness token vanished may take to be reported as exited.
EXIT_GRACE_S = 1.0

#: The command line that starts module ``name`` (resuming at a step, or from the start).
CommandFor = Callable[[str, "int | None"], list[str]]


@dataclasses.dataclass
class RestartEvent:
    """A module that died during the mission, and how the loop recovered."""

    module: str
    step: int
    """The step the restarted module resumed at (the last one it had finished, redone)."""
    reason: str
    died_s: float
    """When the death was noticed, seconds since the supervisor started."""
    ready_s: float | None = None
    """When the restarted module's liveliness token came back."""
    resumed_s: float | None = None
    """When the loop resumed: the restarted module's first output came in."""
    counted: bool = True
    """Whether it counts against --max-restarts (a rollback's restart does not)."""

    def as_dict(self) -> dict[str, Any]:
        d = dataclasses.asdict(self)
        d["death_to_ready_s"] = (self.ready_s - self.died_s) if self.ready_s else None
        d["death_to_resume_s"] = (self.resumed_s - self.died_s) if self.resumed_s else None
        return d


class ProcessSupervisor:
    """The module processes of one mission: start, watch, restart (at most ``max_restarts``
    times each), stop."""

    def __init__(self, names: tuple[str, ...], command_for: CommandFor, logs_dir: Path,
                 max_restarts: int) -> None:
        self.names = names
        self.command_for = command_for
        self.logs_dir = logs_dir
        self.max_restarts = max_restarts
        self.procs: dict[str, subprocess.Popen | LaunchedProcess] = {}
        self._launcher: Launcher | None = None
        self.events: list[RestartEvent] = []
        self.resuming: dict[str, RestartEvent] = {}
        self.alive: set[str] = set()
        self._ever_alive: set[str] = set()
        self._logs: list[IO[str]] = []
        self._t0 = time.monotonic()

    def elapsed(self) -> float:
        return time.monotonic() - self._t0

    # --- what the network says ------------------------------------------------------------

    def mark_alive(self, name: str, alive: bool) -> None:
        """A module's liveliness token appeared (True) or vanished (False)."""
        if alive:
            self.alive.add(name)
            self._ever_alive.add(name)
            event = self.resuming.get(name)
            if event is not None and event.ready_s is None:
                event.ready_s = self.elapsed()
        else:
            self.alive.discard(name)

    def mark_progress(self, name: str, step: int) -> None:
        """Module ``name`` published its last output of ``step``: a restarted one is back."""
        event = self.resuming.get(name)
        if event is not None and step >= event.step:
            event.resumed_s = self.elapsed()
            log.info("%s is back: the loop resumed at step %d, %.2f s after it died", name,
                     step, event.resumed_s - event.died_s)
            del self.resuming[name]

    @property
    def all_alive(self) -> bool:
        return self.alive.issuperset(self.names)

    # --- processes ------------------------------------------------------------------------

    def start_all(self, resume_step: int | None = None) -> None:
        """Start every module, logging to ``logs_dir/<module>.log``; with ``resume_step``
        (a mission manager that was restarted), each resumes at that step."""
        self.logs_dir.mkdir(parents=True, exist_ok=True)
        self._launcher = Launcher(self.logs_dir / "launcher.log")
        for name in self.names:
            self._spawn(name, resume_step)

    def _spawn(self, name: str, resume_step: int | None = None) -> None:
        cmd = self.command_for(name, resume_step)
        # A restarted module appends to the log of the one that died.
        log_path = self.logs_dir / f"{name}.log"
        ours = module_args(cmd)
        try:
            if ours is not None and self._launcher is not None:
                # One of our modules: forked from the launcher, its imports already done.
                self.procs[name] = self._launcher.spawn(ours, log_path,
                                                        append=resume_step is not None)
            else:
                f = open(log_path,  # noqa: SIM115 -- closed in shutdown()
                         "w" if resume_step is None else "a")
                self._logs.append(f)
                self.procs[name] = subprocess.Popen(cmd, stdout=f, stderr=subprocess.STDOUT,
                                                    stdin=subprocess.DEVNULL)
        except OSError as exc:
            raise MissionFailed(f"could not start {name} ({' '.join(cmd)}): {exc}") from None
        log.info("started %s (pid %d)%s", name, self.procs[name].pid,
                 "" if resume_step is None else f", resuming at step {resume_step}")

    def _respawn(self, name: str, step: int) -> None:
        """Start ``name`` again (its old process has exited), resuming at ``step``."""
        self.alive.discard(name)
        self._ever_alive.discard(name)
        self._spawn(name, resume_step=step)

    def dead(self) -> list[tuple[str, str]]:
        """``(module, reason)`` of every module that died: its process exited, or it is alive
        as a process but its token vanished (hung, or cut off: the loop cannot reach it)."""
        out = []
        for name, p in self.procs.items():
            code = p.poll()
            if code is not None:
                out.append((name, f"exited with code {code}"))
            elif name in self._ever_alive and name not in self.alive \
                    and name not in self.resuming:
                # A process that dies closes its links before the kernel reports its exit:
                # give it a moment, so that a death is reported as one, with its exit code.
                try:
                    out.append((name, f"exited with code {p.wait(EXIT_GRACE_S)}"))
                except subprocess.TimeoutExpired:
                    out.append((name, "its liveliness token vanished"))
        return out

    def restart(self, name: str, reason: str, step: int, limit: bool = True) -> RestartEvent:
        """Replace a dead (or live) module with one that resumes at ``step``; raises
        :class:`MissionFailed` once it has died more than ``max_restarts`` times (unless not
        ``limit``: a rollback to the configuration it last ran well on)."""
        died = self.elapsed()
        p = self.procs[name]
        if p.poll() is None:
            p.kill()
            p.wait()
        mine = [e for e in self.events if e.module == name]
        since = max((i for i, e in enumerate(mine) if not e.counted), default=-1)
        restarts = 1 + sum(e.counted for e in mine[since + 1:])  # since the last rollback
        if limit and restarts > self.max_restarts:
            raise MissionFailed(
                f"module {name!r} {reason} during the mission, after {restarts - 1} "
                f"restarts (--max-restarts {self.max_restarts}); its log is "
                f"{self.logs_dir / (name + '.log')}:\n{self.tail(name)}")
        log.warning("module %s %s at step %d; the rover holds still while it restarts "
                    "(restart %d of at most %d)", name, reason, step, restarts,
                    self.max_restarts)
        event = RestartEvent(name, step, reason, died, counted=limit)
        self.events.append(event)
        self.resuming[name] = event
        self._respawn(name, step)
        return event

    def replace(self, names: list[str], step: int) -> None:
        """Stop ``names`` and start them again resuming at ``step`` (with whatever
        configuration ``command_for`` now gives: an in-flight reconfiguration)."""
        for name in names:
            self.procs[name].terminate()
        for name in names:
            try:
                self.procs[name].wait(30)
            except subprocess.TimeoutExpired:
                self.procs[name].kill()
                self.procs[name].wait()
        for name in names:
            self._respawn(name, step)

    def fail_on_exit(self, when: str = "before the mission started",
                     only: str | None = None) -> None:
        """Before the mission starts (or while modules come up with a new configuration), a
        module that exits (of all, or ``only`` this one) is a configuration fault: raise
        :class:`MissionFailed` with the end of its log."""
        for name, p in self.procs.items():
            if only is not None and name != only:
                continue
            code = p.poll()
            if code is not None:
                raise MissionFailed(
                    f"module {name!r} exited with code {code} {when}; its "
                    f"log is {self.logs_dir / (name + '.log')}:\n{self.tail(name)}")

    def shutdown(self, timeout_s: float = 30.0) -> dict[str, int | None]:
        """Wait for the modules to exit (they stop on the final status); terminate the ones
        that do not. Returns each module's exit code."""
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
        self.close_launcher()
        return codes

    def close_launcher(self) -> None:
        if self._launcher is not None:
            self._launcher.close()
            self._launcher = None

    def kill_all(self) -> None:
        for p in self.procs.values():
            if p.poll() is None:
                p.terminate()
        for p in self.procs.values():
            try:
                p.wait(10)
            except subprocess.TimeoutExpired:
                p.kill()

    def tail(self, name: str, lines: int = 15) -> str:
        try:
            text = (self.logs_dir / f"{name}.log").read_text(errors="replace").splitlines()
        except OSError:
            return ""
        return "\n".join("    " + line for line in text[-lines:])
