"""The mission manager's link to Earth: the only bridge between the rover's network and the
ground's.

The rover's processes form one Zenoh network (the mission's session and the modules); the ground
station joins another, which only this bridge's session listens on (``--contact.ground-listen``,
by default a free loopback port). While the link is up, ``OUT/ground.json`` says where it
listens (:data:`LINK_FILE`; ``rovergate ground --mission OUT`` reads it); the bridge removes the
file when it closes. Nothing crosses except what the bridge passes, and it passes traffic only
as the contact plan allows (:mod:`mission.link.contact`):

- Downlink: telemetry goes into the onboard queue (:mod:`mission.link.downlink`) as the mission
  produces it. In each step of a window the bridge radiates items in priority order within the
  step's rate budget; the ground receives them one light time later, in order of sequence
  number, and acknowledges each.
- Uplink: what the ground sends (acknowledgements, commands) waits for a window, is radiated
  in it, and reaches the rover one light time later. Commands are handed to the mission, which
  executes them at the next step boundary and downlinks a ``command_ack``.

The bridge keeps its own clock of link steps: one per mission step, plus one per idle step
while the mission is paused or drains its telemetry after the last step.
"""

from __future__ import annotations

import ipaddress
import json
import logging
import os
import re
import socket
import threading
from collections.abc import Callable
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path
from typing import Any

import numpy as np
import zenoh

from mission.link.contact import ContactConfig, ContactPlan
from mission.link.downlink import DownlinkQueue
from rovergate.access import ground_network
from rovergate.config import SessionConfig
from rovergate.errors import ConfigError
from rovergate.keys import Keys
from rovergate.messages import encode, encode_item
from rovergate.node import Drops, cdr_encoding, decoding
from rovergate.session import TlsFiles, free_loopback_port, open_session
from rovergate.types import (
    SURFACE_DTYPE,
    CommandAck,
    DownlinkAck,
    GroundCommand,
    MissionEvent,
    MissionStatus,
    Pose,
    TelemetryFrame,
)

log = logging.getLogger("rovergate.bridge")

LINK_FILE = "ground.json"
"""In the mission's directory while the link is up: ``endpoints`` (where a station on this
machine connects to the ground network: :func:`connectable`), ``listen`` (where it listens, as
given), ``ground_namespace``, ``rover_namespace``, ``pid`` and ``host`` of the mission
manager, ``started_at`` (ISO 8601)."""

DEFAULT_GROUND_LISTEN = "tcp/127.0.0.1:0"
"""Where the ground network listens when --contact.ground-listen is empty: a free loopback
port."""
ANY_PORT = re.compile(r":0(?=$|#)")
"""Port 0 in an endpoint (before any #-options): take a free port."""
ONBOARD_QUEUE_EVENT = "onboard-queue"
"""The kind of the event radiated first in every window: the onboard queue as JSON (items,
bytes, unacked, dropped) just before the window's radiation."""
PORT_ATTEMPTS = 5
"""Free ports tried for an endpoint with port 0 before giving up."""


def loopback(endpoint: str) -> bool:
    """Whether a Zenoh endpoint (``proto/host:port``) listens on loopback only: a loopback
    address, or ``localhost`` (any other name may resolve anywhere)."""
    host = endpoint.split("/", 1)[-1].split("#", 1)[0].rsplit(":", 1)[0].strip("[]")
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def ground_tls(cfg: ContactConfig) -> TlsFiles | None:
    """The rover's ground-link credentials (--contact.credentials), if any."""
    if cfg.credentials is None:
        return None
    d = Path(cfg.credentials)
    return TlsFiles(d / "ca.pem", d / "rover.pem", d / "rover.key")


def connectable(endpoint: str) -> str:
    """Where a station on this machine reaches an endpoint the bridge listens on: an
    unspecified address (``0.0.0.0``, ``[::]``: every interface) becomes the loopback one, which
    the rover's certificate names (``rovergate credentials``); any other endpoint as given."""
    proto, _, rest = endpoint.partition("/")
    address, hash_, options = rest.partition("#")
    host, _, port = address.rpartition(":")
    bare = host.strip("[]")
    if bare in ("0.0.0.0", "::"):
        host = "127.0.0.1" if bare == "0.0.0.0" else "[::1]"
        return f"{proto}/{host}:{port}{hash_}{options}"
    return endpoint


def check_ground_endpoints(endpoints: tuple[str, ...], authenticated: bool,
                           stations: tuple[str, ...] = ("station",)) -> None:
    """With credentials every ground endpoint is TLS and some station is named; without,
    every endpoint is on loopback. Raises ConfigError naming the first fault."""
    if authenticated and not [s for s in stations if s.strip()]:
        raise ConfigError("--contact.ground-stations is empty: with --contact.credentials, "
                          "name the certificate common names of the stations that may "
                          "command (default: station)")
    for e in endpoints:
        if authenticated and not e.startswith("tls/"):
            raise ConfigError(f"--contact.ground-listen {e}: with --contact.credentials the "
                              "ground link is mutual TLS; use tls/HOST:PORT")
        if not authenticated and not loopback(e):
            raise ConfigError(
                f"--contact.ground-listen {e} is beyond loopback, and the link has no "
                "credentials: anyone who reaches it could command the rover. Create them "
                "with `rovergate credentials --out DIR` and pass --contact.credentials "
                "DIR/rover (with a tls/ endpoint), or listen on 127.0.0.1")


@dataclass
class Delivered:
    """A ground command as it reached the rover."""

    command: GroundCommand
    received_s: float
    """Simulated time of arrival."""


class GroundBridge:
    """The ground-side Zenoh session, the onboard queue, and the link's timing."""

    def __init__(self, cfg: ContactConfig, out: Path, session_cfg: SessionConfig | None = None
                 ) -> None:
        self.cfg = cfg
        self.plan = ContactPlan(cfg)
        self.queue = DownlinkQueue(out / "downlink.sqlite", int(cfg.queue_max_mb * 2**20))
        self.keys = Keys(cfg.ground_namespace)
        base = session_cfg or SessionConfig()
        try:
            self.session, self.endpoints = self._open(base)
        except ConfigError:
            self.queue.close()
            raise
        self.link_file = out / LINK_FILE
        try:
            self._write_link_file(base.namespace)
        except OSError as exc:
            self.session.close()
            self.queue.close()
            raise ConfigError(f"could not write {self.link_file} ({exc}); give --out a "
                              "directory this user can write") from None
        self._pub = self.session.declare_publisher(
            self.keys.key("downlink"), encoding=cdr_encoding("downlink"),
            congestion_control=zenoh.CongestionControl.BLOCK)
        self._lock = threading.Lock()
        self._heard: list[Any] = []
        self.drops = Drops(log, "message from the ground")
        # The ground's transmitter (which this bridge plays) reports each command it radiates.
        self._report = self.session.declare_publisher(
            self.keys.key("uplink_report"), encoding=cdr_encoding("uplink_report"),
            congestion_control=zenoh.CongestionControl.BLOCK)
        self._subs = [self.session.declare_subscriber(self.keys.key(t), self._on_ground(t))
                      for t in ("downlink_ack", "uplink")]
        self._station = False
        self._station_sub = self.session.liveliness().declare_subscriber(
            self.keys.alive("station"), self._on_station, history=True)
        # The ground station watches this token: it goes when the mission manager does.
        self._token = self.session.liveliness().declare_token(self.keys.alive("rover"))
        self.clock = 0
        """Link steps so far (the simulated time is clock * step_s)."""
        self._held: list[Any] = []          # ground transmissions waiting for a window
        self._to_rover: list[tuple[int, Any]] = []   # (arrival clock, ack or command)
        self._to_ground: list[tuple[int, TelemetryFrame]] = []
        self._budget = 0
        self.report_queue = True
        """Radiate the onboard queue's figures at each window's opening (not while the mission
        drains its last telemetry: the report would keep the queue from ever emptying)."""
        self.radiated = 0
        self.dropped_reported = self.queue.dropped

    # --- the ground network ---------------------------------------------------------------

    def _open(self, base: SessionConfig) -> tuple[zenoh.Session, tuple[str, ...]]:
        """The ground-side session and the endpoints it listens on, port 0 replaced by the
        port taken."""
        tls = ground_tls(self.cfg)
        access = ground_network(self.cfg.ground_namespace,
                                tuple(self.cfg.ground_stations) if tls else ())

        def open_on(listen: tuple[str, ...]) -> zenoh.Session:
            return open_session(SessionConfig(
                mode="peer", listen=listen, namespace=self.cfg.ground_namespace,
                multicast_scouting=base.multicast_scouting), access, tls)

        wanted = tuple(self.cfg.ground_listen) or (
            DEFAULT_GROUND_LISTEN.replace("tcp/", "tls/") if tls else DEFAULT_GROUND_LISTEN,)
        check_ground_endpoints(wanted, tls is not None, tuple(self.cfg.ground_stations))
        if not any(ANY_PORT.search(e) for e in wanted):
            try:
                return open_on(wanted), wanted
            except ConfigError:
                raise ConfigError(
                    f"the ground endpoint {', '.join(wanted)} could not be opened (is "
                    "another mission using it?); leave --contact.ground-listen out to take a "
                    "free port, pass another endpoint, or --contact.no-enabled") from None
        # Zenoh binds port 0 itself, but its session API does not say which port it got (only
        # its admin space does, which would have to be opened to the ground network). So: a
        # port free a moment ago, and another if something took it meanwhile (a mission
        # starting at the same moment).
        failure = ""
        for _ in range(PORT_ATTEMPTS):
            listen = tuple(ANY_PORT.sub(f":{free_loopback_port()}", e) for e in wanted)
            try:
                return open_on(listen), listen
            except ConfigError as exc:
                failure = str(exc)
        raise ConfigError(
            f"no free port for the ground endpoint {', '.join(wanted)} in "
            f"{PORT_ATTEMPTS} tries (last: {failure}); pass --contact.ground-listen "
            "tcp/127.0.0.1:PORT, or --contact.no-enabled")

    def _write_link_file(self, rover_namespace: str) -> None:
        """OUT/ground.json, written whole or not at all (temp file and rename), so that a
        ground station never reads half of it."""
        # The station connects to what the file says: a wildcard address is where the bridge
        # listens, not one anybody can connect to (a station elsewhere is given --connect).
        self._link = {"endpoints": [connectable(e) for e in self.endpoints],
                      "listen": list(self.endpoints),
                      "ground_namespace": self.cfg.ground_namespace,
                      "rover_namespace": rover_namespace, "pid": os.getpid(),
                      "host": socket.gethostname(),
                      "started_at": datetime.now().astimezone().isoformat(timespec="seconds")}
        tmp = self.link_file.with_name(f".{LINK_FILE}.tmp-{os.getpid()}")
        tmp.write_text(json.dumps(self._link, indent=1) + "\n")
        os.replace(tmp, self.link_file)

    def _remove_link_file(self) -> None:
        """Remove OUT/ground.json if it is still this mission's (another mission given the
        same --out may have written its own since)."""
        try:
            if json.loads(self.link_file.read_text()) == self._link:
                self.link_file.unlink()
        except (OSError, ValueError):
            pass

    @property
    def dropped(self) -> int:
        """Messages from the ground that did not decode."""
        return self.drops.count

    def _on_ground(self, topic: str) -> Callable[[zenoh.Sample], None]:
        def heard(step: int, value: Any, sample: zenoh.Sample) -> None:
            with self._lock:
                self._heard.append(value)
        return decoding(topic, self.keys.key(topic), self.drops, heard)

    def _on_station(self, sample: zenoh.Sample) -> None:
        with self._lock:
            self._station = sample.kind == zenoh.SampleKind.PUT

    @property
    def station_connected(self) -> bool:
        with self._lock:
            return self._station

    # --- telemetry ------------------------------------------------------------------------

    def status(self, status: MissionStatus) -> None:
        self._put("status", status.step, status)

    def pose(self, step: int, pose: Pose) -> None:
        self._put("pose", step, (step, pose))

    def event(self, step: int, kind: str, detail: str = "") -> None:
        log.info("event at step %d: %s %s", step, kind, detail)
        self._put("event", step, MissionEvent(step, kind, detail))

    def command_ack(self, ack: CommandAck) -> None:
        self._put("command_ack", ack.step, ack)

    def map_snapshot(self, step: int, surface: np.ndarray) -> None:
        """The observed surface, thinned evenly to ``map_snapshot_points`` (it supersedes an
        older snapshot not yet radiated)."""
        n = self.cfg.map_snapshot_points
        if len(surface) > n:
            surface = surface[np.linspace(0, len(surface) - 1, n).astype(np.int64)]
        self._put("map", step, (step, np.ascontiguousarray(surface, dtype=SURFACE_DTYPE)))

    def _put(self, kind: str, step: int, value: Any) -> None:
        msgtype, payload = encode_item(kind, value)
        self.queue.put(kind, msgtype, step, payload)

    # --- the link -------------------------------------------------------------------------

    def tick(self) -> list[Delivered]:
        """Advance the link by one step; returns the commands that reached the rover."""
        k = self.clock
        is_open = self.plan.is_open(k)
        light = self.plan.light_steps
        with self._lock:
            heard, self._heard = self._heard, []
        self._held.extend(heard)
        if is_open and self._held:  # the ground radiates what it has
            self._to_rover.extend((k + light, v) for v in self._held)
            for v in self._held:
                if isinstance(v, GroundCommand):
                    self._report.put(encode("uplink_report", CommandAck(
                        v.id, v.verb, "radiated", k, (k + light) * self.cfg.step_s, "")))
            self._held = []
        arrived = [v for t, v in self._to_rover if t <= k]
        self._to_rover = [(t, v) for t, v in self._to_rover if t > k]
        commands = []
        for value in arrived:
            if isinstance(value, DownlinkAck):
                self.queue.ack(value.seqs)
            elif isinstance(value, GroundCommand):
                commands.append(Delivered(value, k * self.cfg.step_s))
        dropped = self.queue.dropped
        if dropped > self.dropped_reported:
            self.event(k, "telemetry-dropped",
                       f"{dropped - self.dropped_reported} status/pose samples dropped over "
                       f"the {self.cfg.queue_max_mb:g} MB bound")
            self.dropped_reported = dropped
        if is_open and not self.plan.is_open(k - 1) and self.report_queue:
            # At each window's opening, the onboard queue as it stands (the ground's console
            # shows what waits aboard).
            self._put("event", k, MissionEvent(k, ONBOARD_QUEUE_EVENT, json.dumps(
                {"link_step": k, "items": len(self.queue), "bytes": self.queue.nbytes(),
                 "unacked": self.queue.unacked(), "dropped": self.queue.dropped})))
        if is_open:
            self._budget += self.plan.bytes_per_step
            items = self.queue.take(self._budget, k * self.cfg.step_s, self._ack_due_s(k))
            for item in items:
                self._budget -= len(item.payload)
                self._to_ground.append((k + light, TelemetryFrame(
                    item.seq, item.kind, item.msgtype, item.step, k * self.cfg.step_s,
                    item.payload)))
            self.radiated += len(items)
        else:
            self._budget = 0
        due = [f for t, f in self._to_ground if t <= k]
        self._to_ground = [(t, f) for t, f in self._to_ground if t > k]
        for frame in sorted(due, key=lambda f: f.seq):
            self._pub.put(encode("downlink", frame))
        self.clock += 1
        return commands

    def _ack_due_s(self, k: int) -> float:
        """When the acknowledgement of a frame radiated at link step k should be back: it
        reaches the ground at k + L, the ground answers at once (the bridge hears it by the
        step after, one step of slack for the ground's own latency), the answer waits for a
        window and travels L back."""
        light = self.plan.light_steps
        # No window left: after the mission the link is held open (ContactPlan.hold_open),
        # so the answer can come at once then; it is radiated again if it does not.
        window = self.plan.next_open(k + light + 2)
        if window is None:
            window = k + light + 2
        return (window + light) * self.cfg.step_s

    # --- the mission manager's checkpoint (mission.runtime.checkpoint) ----------------------------

    def snapshot(self) -> dict[str, Any]:
        """The link's state besides the onboard queue (which is its own file): the clock and
        what is on its way. What the ground sent since the last tick is not in it: a manager
        that dies loses it, as a radio loses what arrives while the receiver is off."""
        return {"clock": self.clock, "held": list(self._held), "to_rover": list(self._to_rover),
                "to_ground": list(self._to_ground), "budget": self._budget,
                "radiated": self.radiated, "dropped": self.dropped,
                "dropped_reported": self.dropped_reported}

    def restore(self, snap: dict[str, Any]) -> None:
        self.clock = int(snap["clock"])
        self._held = list(snap["held"])
        self._to_rover = list(snap["to_rover"])
        self._to_ground = list(snap["to_ground"])
        self._budget = int(snap["budget"])
        self.radiated = int(snap["radiated"])
        self.drops.count = int(snap["dropped"])
        self.dropped_reported = int(snap["dropped_reported"])

    @property
    def settled(self) -> bool:
        """Nothing left to send, nothing on its way either way (a command the ground sent
        included), every item acknowledged."""
        with self._lock:
            heard = bool(self._heard)
        return (len(self.queue) == 0 and not self._to_ground and not self._to_rover
                and not self._held and not heard)

    def close(self) -> None:
        # The file goes first: whoever reads it from now on is told the mission has ended.
        self._remove_link_file()
        for s in self._subs:
            s.undeclare()
        self._report.undeclare()
        self._station_sub.undeclare()
        self._token.undeclare()
        self.session.close()
        self.queue.close()
