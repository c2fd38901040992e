"""Mission operations at the step boundary: the link to the ground, and ground commands.

:class:`Operations` sits in the process set's mission loop (:func:`mission.loop.run_mission`),
and acts on the mission through :class:`MissionControl` (the process set implements it).
At the top of every step it advances the link (:class:`mission.bridge.GroundBridge`) and
executes the commands that have reached the rover; after every step it queues that step's
telemetry. While paused, it keeps the link's clock running in idle steps (the rover holds
still), so that a ``resume`` can come up in a later window.

Commands that change the configuration (``set``, ``condition``, ``planner``) restart the
modules concerned with the new configuration; they rebuild their state from the mission's
journal, so the new setting applies from the next step on, as if it had always been set
(the gate's filter, for instance, recounts every frustum so far with the new K).
"""

from __future__ import annotations

import dataclasses
import json
import logging
import time
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from mission.bridge import Delivered, GroundBridge
from mission.supervisor import RestartEvent
from rovergate.conditions import get_condition
from rovergate.config import MissionConfig, check_values, from_dict, to_dict
from rovergate.errors import ConfigError, UnknownNameError
from rovergate.graph import readers
from rovergate.module import STOP
from rovergate.types import CommandAck, MissionStatus, Pose

log = logging.getLogger("rovergate.operations")

#: Config sections the ground may change in flight; the modules built from them restart
#: (:func:`rovergate.graph.readers`).
SETTABLE = ("gate", "planner")


class CommandError(ValueError):
    """A ground command the rover refuses (its acknowledgement says why)."""


def apply_settings(cfg: MissionConfig, pairs: list[str]) -> tuple[MissionConfig, set[str]]:
    """``section.field=value`` pairs applied to a copy of ``cfg``; returns it and the modules
    to restart. Values are read as JSON where they parse (3, 0.05, true), else as text."""
    data = to_dict(cfg)
    modules: set[str] = set()
    for pair in pairs:
        key, _, raw = pair.partition("=")
        section, _, name = key.strip().partition(".")
        if section not in SETTABLE or name not in data[section]:
            raise CommandError(f"cannot set {key!r} in flight; settable: " + ", ".join(
                f"{s}.<field>" for s in SETTABLE))
        try:
            value: Any = json.loads(raw)
        except ValueError:
            value = raw
        old = data[section][name]
        if isinstance(old, float) and isinstance(value, int) and not isinstance(value, bool):
            value = float(value)
        if type(value) is not type(old):
            raise CommandError(f"{key} takes a {type(old).__name__}, got {raw!r}")
        data[section][name] = value
        modules.update(readers(section))
    new = from_dict(MissionConfig, data)
    try:
        check_values(new)  # a value no module can run with is refused, not restarted on
    except ConfigError as exc:
        raise CommandError(str(exc)) from None
    return new, modules


class MissionControl(Protocol):
    """What ground commands act through: the process set's side of operations."""

    @property
    def cfg(self) -> MissionConfig:
        """The configuration as it stands."""
        ...

    out: Path
    """The mission's output directory (the downlink queue lives there)."""

    @property
    def restart_events(self) -> list[RestartEvent]:
        """Modules that died and were restarted, in order."""
        ...

    def publish_status(self, status: MissionStatus) -> None:
        """Publish a status (``paused`` keep-alives while the ground holds the rover)."""
        ...

    def check_health(self) -> bool:
        """Restart every module that died; True when one was."""
        ...

    def reconfigure(self, cfg: MissionConfig, modules: list[str], step: int) -> None:
        """Restart ``modules`` with ``cfg`` at the boundary before ``step``."""
        ...


class Operations:
    """The link, pause and abort, and in-flight reconfiguration of one process-set mission."""

    @property
    def cfg(self) -> MissionConfig:
        """The mission's configuration as it stands (commands change it)."""
        return self.control.cfg

    def __init__(self, control: MissionControl) -> None:
        self.control = control
        cfg = control.cfg
        self.bridge = GroundBridge(cfg.contact, control.out, cfg.session)
        c, plan = cfg.contact, self.bridge.plan
        windows = plan.windows_between(0, cfg.steps)
        log.info("link to the ground on %s (written to %s; follow it with `rovergate ground "
                 "--mission %s`): %d windows in %d steps (first %s), light time %d steps, "
                 "%g kbit/s; %d items already queued in %s", ", ".join(self.bridge.endpoints),
                 self.bridge.link_file, control.out, len(windows), cfg.steps,
                 windows[0] if windows else "none", plan.light_steps, c.downlink_kbps,
                 len(self.bridge.queue), self.bridge.queue.path)
        self.paused = False
        self.abort = False
        self.events_sent = 0
        self.commands: list[dict[str, Any]] = []
        self._executed: set[int] = set()
        self.reconfigurations: list[dict[str, Any]] = []

    # --- the step boundary ----------------------------------------------------------------

    def boundary(self, step: int) -> None:
        """Advance the link one step and execute what came up; while paused, hold here."""
        self._handle(step, self.bridge.tick())
        last_keepalive = 0.0
        while self.paused and not self.abort:
            if STOP.is_set():  # Ctrl-C or SIGTERM while the ground holds the rover
                raise KeyboardInterrupt
            if time.monotonic() - last_keepalive > 1.0:
                # Modules stop when no input comes for long; "paused" tells them to wait on.
                self.control.publish_status(MissionStatus(step, self.cfg.steps, "paused",
                                                      self.cfg.condition, 0.0, 0))
                last_keepalive = time.monotonic()
            time.sleep(self.cfg.contact.idle_step_wall_s)
            self.control.check_health()
            self._handle(step, self.bridge.tick())

    def _handle(self, step: int, delivered: list[Delivered]) -> None:
        self._report_restarts()
        for d in delivered:
            c = d.command
            if c.id in self._executed:  # the ground sent it again: it runs once
                continue
            self._executed.add(c.id)
            try:
                detail = self._execute(step, c.verb, list(c.args))
                state = "executed"
            except CommandError as exc:
                detail, state = str(exc), "rejected"
            log.info("ground command %d (%s %s) %s at step %d: %s", c.id, c.verb,
                     " ".join(c.args), state, step, detail)
            self.commands.append({"id": c.id, "verb": c.verb, "args": list(c.args),
                                  "state": state, "step": step, "received_s": d.received_s,
                                  "link_step": self.bridge.clock - 1, "detail": detail})
            self.bridge.command_ack(CommandAck(c.id, c.verb, state, step, d.received_s,
                                               detail))

    def _execute(self, step: int, verb: str, args: list[str]) -> str:
        if verb == "pause":
            self.paused = True
            self.bridge.event(step, "paused", "the rover holds still until resume")
            return f"paused before step {step}"
        if verb == "resume":
            if not self.paused:
                raise CommandError("not paused")
            self.paused = False
            self.bridge.event(step, "resumed")
            return f"resumed at step {step}"
        if verb == "abort":
            self.abort = True
            return f"aborted before step {step}"
        if verb in ("condition", "planner") and not args:
            raise CommandError(f"{verb} needs an argument (e.g. condition gated, planner beam)")
        if verb == "set":
            cfg, modules = apply_settings(self.cfg, args)
        elif verb == "condition":
            try:
                get_condition(args[0])
            except UnknownNameError as exc:
                raise CommandError(str(exc)) from None
            cfg = dataclasses.replace(self.cfg, condition=args[0])
            modules = set(readers("condition"))
        elif verb == "planner":
            if args[0] == "cmd":
                if len(args) < 2:
                    raise CommandError("planner cmd needs a command line")
                planner = dataclasses.replace(self.cfg.planner, command=" ".join(args[1:]))
            else:
                from planner.planner import PLANNERS
                if args[0] not in ("auto", *PLANNERS):
                    raise CommandError(f"unknown planner {args[0]!r}; one of: auto, "
                                       f"{', '.join(PLANNERS)}, or cmd <command line>")
                planner = dataclasses.replace(self.cfg.planner, name=args[0], command="")
            cfg, modules = dataclasses.replace(self.cfg, planner=planner), set(readers("planner"))
        else:
            raise CommandError(f"unknown verb {verb!r}")
        t0 = time.monotonic()
        self.control.reconfigure(cfg, sorted(modules), step)
        seconds = time.monotonic() - t0
        self.reconfigurations.append({"step": step, "verb": verb, "args": args,
                                      "modules": sorted(modules), "seconds": seconds})
        self.bridge.event(step, "reconfigured",
                          f"{verb} {' '.join(args)}: restarted {', '.join(sorted(modules))} "
                          f"in {seconds:.1f} s")
        return f"{', '.join(sorted(modules))} restarted with {verb} {' '.join(args)}"

    def _report_restarts(self) -> None:
        events = self.control.restart_events
        for e in events[self.events_sent:]:
            self.bridge.event(e.step, "module-restarted",
                              f"{e.module} {e.reason}; restarted, resuming at step {e.step}")
        self.events_sent = len(events)

    # --- telemetry ------------------------------------------------------------------------

    def after_step(self, status: MissionStatus, base: Pose, surface: np.ndarray) -> None:
        """Queue one step's telemetry (a map snapshot just before a window opens)."""
        self.bridge.status(status)
        self.bridge.pose(status.step, base)
        if self.bridge.plan.is_open(self.bridge.clock) and not \
                self.bridge.plan.is_open(self.bridge.clock - 1):
            self.bridge.map_snapshot(status.step, surface)

    def finish(self, status: MissionStatus) -> dict[str, Any]:
        """The final status and event; then, with a ground station on the link, keep the
        clock running (idle steps) until everything is acknowledged or ``drain_steps`` ran
        out. Returns the link's figures for metrics.json."""
        self._report_restarts()
        self.bridge.status(status)
        self.bridge.event(status.step, f"mission-{status.state}",
                          f"coverage {status.coverage:.3f}, {status.collisions} collisions")
        idle = 0
        t0 = time.monotonic()
        while self.bridge.station_connected and not self.bridge.settled and \
                idle < self.cfg.contact.drain_steps and not STOP.is_set():
            self.bridge.tick()
            idle += 1
            time.sleep(self.cfg.contact.idle_step_wall_s)
        left = len(self.bridge.queue)
        if left:
            log.info("%d telemetry items stay in the onboard queue %s (%s)", left,
                     self.bridge.queue.path, "no ground station on the link"
                     if not self.bridge.station_connected else
                     f"not acknowledged after {idle} idle steps")
        return {"link_steps": self.bridge.clock, "drain_idle_steps": idle,
                "drain_wall_s": time.monotonic() - t0, "radiated": self.bridge.radiated,
                "undelivered": left, "dropped_telemetry": self.bridge.queue.dropped,
                "dropped_ground_messages": self.bridge.dropped,
                "commands": self.commands, "reconfigurations": self.reconfigurations}

    def close(self) -> None:
        self.bridge.close()
