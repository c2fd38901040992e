"""Mission operations at the step boundary: the link to the ground, and ground commands.

:class:`Operations` sits in the process set's mission loop
(:func:`mission.runtime.loop.run_mission`), and acts on the mission through
:class:`MissionControl` (the process set implements it).
At the top of every step it advances the link (:class:`mission.link.bridge.GroundBridge`) and
executes the commands that have reached the rover; after every step it queues that step's
telemetry. While paused, it keeps the link's clock running in idle steps (the rover holds
still), so that a ``resume`` can come up in a later window.

Nothing from the ground runs a program the launch did not name: ``planner NAME`` chooses a
built-in planner or one of ``--planner.programs``, and ``set`` changes only the fields of
:data:`mission.link.commands.IN_FLIGHT`, within their ranges (the one allowlist, which the
ground station and its console check too).

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

from mission.link.bridge import Delivered, GroundBridge
from mission.link.commands import (
    DICTIONARY_EVENT,
    IN_FLIGHT,
    CommandError,
    Setting,
    local_dictionary,
    setting_value,
)
from mission.link.contact import CONTACT_PLAN_EVENT
from mission.runtime.supervisor import RestartEvent
from rovergate.conditions import get_condition
from rovergate.config import MissionConfig, check_values, from_dict, planner_programs, to_dict
from rovergate.errors import ConfigError, ReconfigurationFailed, UnknownNameError
from rovergate.graph import readers
from rovergate.logs import plural
from rovergate.module import STOP
from rovergate.types import CommandAck, MissionStatus, Pose

log = logging.getLogger("rovergate.operations")


def apply_settings(cfg: MissionConfig, pairs: list[str]) -> tuple[MissionConfig, set[str]]:
    """``section.field=value`` pairs (fields of :data:`IN_FLIGHT`) applied to a copy of
    ``cfg``; returns it and the modules to restart. Values are read as JSON numbers; an
    integer field takes only an integer, a real one either."""
    data = to_dict(cfg)
    modules: set[str] = set()
    for pair in pairs:
        key, _, raw = pair.partition("=")
        key = key.strip()
        if key not in IN_FLIGHT:
            raise CommandError(f"cannot set {key!r} in flight; settable: "
                               + ", ".join(IN_FLIGHT))
        section, _, name = key.partition(".")
        old = data[section][name]
        least, most = IN_FLIGHT[key]
        kind = "integer" if isinstance(old, int) else "number"
        data[section][name] = setting_value(Setting(key, kind, least, most), raw)
        modules.update(readers(section))
    new = from_dict(MissionConfig, data)
    try:
        check_values(new)  # a value no module can run with is refused, not restarted on
    except ConfigError as exc:
        raise CommandError(str(exc)) from None
    return new, modules


def choose_planner(cfg: MissionConfig, name: str) -> MissionConfig:
    """``planner NAME`` from the ground: a built-in planner, or a program fixed at launch
    (``--planner.programs``). The ground never sends a command line."""
    from planner.planner import planner_names
    programs = planner_programs(cfg.planner)
    if name in ("auto", *planner_names()):
        planner = dataclasses.replace(cfg.planner, name=name, command="")
    elif name in programs:
        planner = dataclasses.replace(cfg.planner, command=programs[name])
    else:
        why = ("the ground cannot send a command line; " if name == "cmd" else
               f"unknown planner {name!r}; ")
        names = ", ".join(["auto", *planner_names(), *programs])
        raise CommandError(why + "choose one of: " + names
                           + (" (programs are fixed at launch: --planner.programs "
                              "NAME=COMMAND)"))
    return dataclasses.replace(cfg, planner=planner)


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

    rollbacks: list[tuple[int, str]]
    """Reconfigurations undone because their modules kept dying or fell silent: the step
    and the reason."""

    def reconfigure(self, cfg: MissionConfig, modules: list[str], step: int) -> None:
        """Restart ``modules`` with ``cfg`` at the boundary before ``step``; if they do not
        come up, restart them with the previous configuration and raise
        :class:`ReconfigurationFailed`."""
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
                 "--mission %s`): %s in %s (first %s), light time %s, "
                 "%g kbit/s; %s already queued in %s; %s", ", ".join(self.bridge.endpoints),
                 self.bridge.link_file, control.out, plural(len(windows), "window"),
                 plural(cfg.steps, "step"), windows[0] if windows else "none",
                 plural(plan.light_steps, "step"), c.downlink_kbps,
                 plural(len(self.bridge.queue), "item"), self.bridge.queue.path,
                 plan.end_of_mission(cfg.steps, c.drain_steps))
        if c.credentials is None:
            log.warning("the ground link is not authenticated (no --contact.credentials), so "
                        "it listens on loopback only: any process on this machine can command "
                        "the rover (docs/security.md)")
        else:
            log.info("the ground link is mutual TLS with the credentials in %s: only a "
                     "station whose certificate names %s may command", c.credentials,
                     " or ".join(c.ground_stations))
        self.paused = False
        self.abort = False
        self.events_sent = 0
        self.rollbacks_sent = 0
        self.commands: list[dict[str, Any]] = []
        self._executed: set[int] = set()
        self.reconfigurations: list[dict[str, Any]] = []

    def event(self, step: int, kind: str, detail: str = "") -> None:
        """Send the ground a mission event (``mission-started``, ``mission-resumed``, ...)."""
        self.bridge.event(step, kind, detail)

    def describe_link(self, step: int) -> None:
        """Send the ground the contact plan and the commands this rover takes (after the
        mission-started or -resumed event): the console shows the plan and composes commands
        from the dictionary."""
        self.bridge.event(step, CONTACT_PLAN_EVENT, json.dumps(
            self.bridge.plan.describe(self.cfg.steps + self.cfg.contact.drain_steps),
            separators=(",", ":")))
        programs = tuple(planner_programs(self.cfg.planner))
        self.bridge.event(step, DICTIONARY_EVENT,
                          local_dictionary(programs, "rover").to_json())

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
            except (ValueError, TypeError, OverflowError, RecursionError) as exc:
                # A command no check foresaw is refused, never the end of the mission.
                log.exception("ground command %d (%s) failed", c.id, c.verb)
                detail, state = f"refused: {type(exc).__name__}: {exc}"[:300], "rejected"
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
        if verb in ("condition", "planner") and len(args) != 1:
            raise CommandError(f"{verb} takes one name (e.g. condition gated, planner beam)")
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
            if len(args) != 1:
                raise CommandError("planner takes one name (e.g. planner beam); the ground "
                                   "cannot send a command line")
            cfg, modules = choose_planner(self.cfg, args[0]), set(readers("planner"))
        else:
            raise CommandError(f"unknown verb {verb!r}")
        t0 = time.monotonic()
        try:
            self.control.reconfigure(cfg, sorted(modules), step)
        except ReconfigurationFailed as exc:
            self.bridge.event(step, "reconfiguration-rolled-back", str(exc))
            raise CommandError(str(exc)) from None
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
        for step, why in self.control.rollbacks[self.rollbacks_sent:]:
            self.reconfigurations.append({"step": step, "verb": "rollback", "args": [],
                                          "detail": why})
            self.bridge.event(step, "reconfiguration-rolled-back", why)
        self.rollbacks_sent = len(self.control.rollbacks)

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
                          f"coverage {status.coverage:.3f}, "
                          f"{plural(status.collisions, 'collision')}")
        idle = 0
        t0 = time.monotonic()
        self.bridge.report_queue = False
        while self.bridge.station_connected and not self.bridge.settled and \
                idle < self.cfg.contact.drain_steps and not STOP.is_set():
            if self.bridge.plan.next_open(self.bridge.clock) is None:
                self.bridge.plan.hold_open(self.bridge.clock)  # no window left: stay up
            self._too_late(status, self.bridge.tick())
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

    def _too_late(self, status: MissionStatus, delivered: list[Delivered]) -> None:
        """Commands that reach the rover after its last step are acknowledged as rejected
        (the ground learns that they did not run), never dropped unanswered."""
        for d in delivered:
            c = d.command
            if c.id in self._executed:
                continue
            self._executed.add(c.id)
            detail = f"the mission had ended ({status.state} at step {status.step})"
            log.info("ground command %d (%s %s) rejected after the mission: %s", c.id, c.verb,
                     " ".join(c.args), detail)
            self.commands.append({"id": c.id, "verb": c.verb, "args": list(c.args),
                                  "state": "rejected", "step": status.step,
                                  "received_s": d.received_s,
                                  "link_step": self.bridge.clock - 1, "detail": detail})
            self.bridge.command_ack(CommandAck(c.id, c.verb, "rejected", status.step,
                                               d.received_s, detail))

    # --- the mission manager's checkpoint (mission.runtime.checkpoint) ----------------------------

    def snapshot(self) -> dict[str, Any]:
        """Pause, the commands run so far (each runs once) and the link's state."""
        return {"paused": self.paused, "events_sent": self.events_sent,
                "commands": list(self.commands), "executed": sorted(self._executed),
                "reconfigurations": list(self.reconfigurations),
                "bridge": self.bridge.snapshot()}

    def restore(self, snap: dict[str, Any]) -> None:
        self.paused = bool(snap["paused"])
        self.commands = list(snap["commands"])
        self._executed = set(snap["executed"])
        self.reconfigurations = list(snap["reconfigurations"])
        self.bridge.restore(snap["bridge"])
        # Restart events of the manager that died were reported by it (or are in its
        # record); the new supervisor counts its own from 0.
        self.events_sent = self.rollbacks_sent = 0

    def close(self) -> None:
        self.bridge.close()
