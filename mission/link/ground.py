"""``rovergate ground``: the ground station, a process of its own on the ground network.

It connects to the mission manager's ground endpoint, which it finds in the mission's
``ground.json`` (``--mission OUT``, by default ``runs/latest``) or is given (``--connect``; it
may run on another machine), shows and records every telemetry item that comes down,
acknowledges each by sequence number, and sends commands up. What it received is kept in
``OUT/received.jsonl`` (one line per sequence number, never two) and the newest map snapshot in
``OUT/map_latest.npy``; both survive a restart of the station, which then goes on where it
stopped.

Commands (``--send`` at start, repeated or with several quoted commands, or typed on standard
input, one per line)::

    pause | resume | abort
    set gate.k=3 [planner.n_candidates=16 ...]
    condition gated
    planner beam | planner frontier   (a built-in planner, or a program the mission named
                                       at launch with --planner.programs; never a command line)

A command travels only in a contact window and reaches the rover one light time later; the
rover executes it at the next step boundary and downlinks a ``command_ack``. Every command is
checked against the allowlist (:mod:`mission.link.commands`) before it is queued: one the rover
would refuse is refused here, with the same reason, and never sent.

``--web`` serves the operator's console (:mod:`mission.link.console`) from the same process:
the same store, the same allowlist, the same uplink.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import queue
import socket
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import tyro
import zenoh

from mission.link.bridge import LINK_FILE
from mission.link.commands import (
    VERBS,
    CommandError,
    Dictionary,
    command_line,
    local_dictionary,
    parse_command,
    read_command,
)
from mission.link.console import Console, ConsoleConfig, check_web
from mission.link.store import GroundStore, read_jsonl
from rovergate.config import SessionConfig
from rovergate.errors import ConfigError
from rovergate.keys import Keys
from rovergate.logs import init_logging
from rovergate.messages import MessageError, decode_item, encode
from rovergate.module import STOP
from rovergate.node import cdr_encoding, check_and_decode
from rovergate.session import TLS_CONNECT_TIMEOUT_S, TlsFiles, open_session
from rovergate.types import (
    CommandAck,
    DownlinkAck,
    GroundCommand,
    MissionEvent,
    MissionStatus,
    Pose,
    TelemetryFrame,
)

__all__ = ["VERBS", "GroundConfig", "GroundStation", "parse_command", "resolve_link", "main"]


@dataclass
class GroundConfig:
    """The ground station."""

    mission: Path = Path("runs/latest")
    """The mission's directory (its --out; this default is `rovergate run`'s): connect to the
    endpoints its ground.json names (the mission writes it while its link to the ground is
    up)."""
    connect: tuple[str, ...] = ()
    """The mission manager's ground endpoints (its --contact.ground-listen), e.g.
    tcp/ROVER:7448. Given, they win over --mission."""
    credentials: Path | None = None
    """Directory of this station's credentials (ca.pem, station.pem, station.key; made by
    `rovergate credentials`), for a mission whose ground link is mutual TLS."""
    namespace: str = ""
    """Prefix of the ground network's keys (the mission's --contact.ground-namespace). Empty:
    the one in the mission's ground.json, or `ground` with --connect."""
    out: Path = Path("runs/ground")
    """Where the station records what came down (received.jsonl, map_latest.npy)."""
    send: tyro.conf.UseAppendAction[tuple[tuple[str, ...], ...]] = ()
    """Commands to send at start, each one quoted, in order: --send pause --send resume, or
    --send "set gate.k=3" pause."""
    stdin: bool = True
    """Read further commands from standard input, one per line."""
    until_mission_ends: bool = True
    """Exit once the mission manager has gone (after it drained its telemetry); with
    --no-until-mission-ends the station, and its console, stay up until Ctrl-C or
    --timeout-s."""
    timeout_s: float = 0.0
    """Exit after this many seconds (0: no limit), whether or not the mission was reached."""
    web: bool = False
    """Serve the operator's console (a page in a browser) beside the terminal."""
    web_host: str = "127.0.0.1"
    """Where the console listens. Beyond loopback it needs --web-token-file (and, to keep the
    token off the wire, --web-cert and --web-key)."""
    web_port: int = 0
    """The console's port (0: a free one; the log says which)."""
    web_token_file: Path | None = None
    """A file holding the console's access token (one line, at least 16 characters): a browser
    opens http://HOST:PORT/?token=TOKEN once, and is let in from then on."""
    web_cert: Path | None = None
    """PEM certificate to serve the console over HTTPS (with --web-key)."""
    web_key: Path | None = None
    """PEM private key of --web-cert."""
    web_client_ca: Path | None = None
    """With --web-cert/--web-key: let in only browsers presenting a certificate this CA signed
    (the mission's ca.pem: the station's certificate from `rovergate credentials`)."""

    @property
    def commands(self) -> list[str]:
        """The --send commands in the order given (each --send may carry several)."""
        return [line for group in self.send for line in group]


class LinkFileError(ConfigError):
    """No usable ground.json where the station looked (the message says how to go on)."""


def _running_here(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # someone else's process: it runs
        return True
    return True


def resolve_link(cfg: GroundConfig) -> GroundConfig:
    """``cfg`` with the endpoints and the namespace to use: --connect as given, else those in
    the mission's ground.json (:data:`mission.link.bridge.LINK_FILE`). A missing, malformed or
    stale file raises :class:`LinkFileError` with one line."""
    if cfg.connect:
        return replace(cfg, namespace=cfg.namespace or "ground")
    path = Path(cfg.mission) / LINK_FILE
    fix = "start a mission first, or pass --mission OUT or --connect tcp/HOST:PORT"
    try:
        link = json.loads(path.read_text())
    except FileNotFoundError:
        raise LinkFileError(f"{path} does not exist (no mission has its link to the "
                            f"ground up in {cfg.mission}); {fix}") from None
    except (OSError, ValueError) as exc:
        raise LinkFileError(f"{path} cannot be read as JSON ({exc}); {fix}") from None
    endpoints = link.get("endpoints") if isinstance(link, dict) else None
    namespace = link.get("ground_namespace") if isinstance(link, dict) else None
    if not (isinstance(endpoints, list) and endpoints
            and all(isinstance(e, str) and e for e in endpoints)
            and isinstance(namespace, str) and namespace):
        raise LinkFileError(f"{path} is not a mission's ground link file (it needs "
                            f"\"endpoints\" and \"ground_namespace\"); {fix}")
    pid = link.get("pid")
    if isinstance(pid, int) and link.get("host") == socket.gethostname() \
            and not _running_here(pid):
        raise LinkFileError(f"{path} was left by a mission (pid {pid}) that is no "
                            f"longer running; {fix}")
    return replace(cfg, connect=tuple(endpoints), namespace=cfg.namespace or namespace)


def station_tls(cfg: GroundConfig) -> TlsFiles | None:
    """The station's credentials (--credentials); ConfigError when the link needs them (a
    tls/ endpoint) and none were given, or when given for a link without TLS."""
    tls_link = any(e.startswith("tls/") for e in cfg.connect)
    if cfg.credentials is None:
        if tls_link:
            raise ConfigError("the mission's ground link is mutual TLS "
                              f"({', '.join(cfg.connect)}); pass --credentials DIR/station "
                              "(made by `rovergate credentials`)")
        return None
    if not tls_link:
        raise ConfigError(f"--credentials is for a tls/ link, and {', '.join(cfg.connect)} is "
                          "not one; connect to the mission's tls/ endpoint")
    d = Path(cfg.credentials)
    tls = TlsFiles(d / "ca.pem", d / "station.pem", d / "station.key")
    tls.check()
    return tls


def summarize(kind: str, value) -> str:
    if isinstance(value, MissionStatus):
        return (f"{value.state} step {value.step}/{value.steps_total} coverage "
                f"{value.coverage:.3f} collisions {value.collisions} ({value.condition})")
    if isinstance(value, Pose):
        x, y, z = value.position
        return f"base at ({x:.2f}, {y:.2f}, {z:.2f}) yaw {np.degrees(value.yaw):.0f} deg"
    if isinstance(value, MissionEvent):
        return f"{value.kind}: {value.detail}" if value.detail else value.kind
    if isinstance(value, CommandAck):
        return (f"command {value.id} ({value.verb}) {value.state} at step {value.step}"
                + (f": {value.detail}" if value.detail else ""))
    if isinstance(value, np.ndarray):
        return f"map snapshot of {len(value)} points"
    return kind


class GroundStation:
    """Records downlinked items once each, acknowledges them, sends commands; keeps the
    ground's picture of the mission (:attr:`store`) for the console."""

    def __init__(self, cfg: GroundConfig, log: logging.Logger) -> None:
        self.cfg = cfg
        self.log = log
        self.keys = Keys(cfg.namespace)
        cfg.out.mkdir(parents=True, exist_ok=True)
        self.received_path = cfg.out / "received.jsonl"
        self.seen: set[int] = set()
        self.next_id = 1
        for row in read_jsonl(self.received_path):
            self.seen.add(int(row["seq"]))
        sent_path = cfg.out / "sent.jsonl"
        for row in read_jsonl(sent_path):
            self.next_id = max(self.next_id, int(row["id"]) + 1)
        # The commands this installation knows until the rover's own list comes down.
        self.store = GroundStore(cfg.out, local_dictionary())
        self.duplicates = 0
        self.dropped = 0
        self.on_status: Callable[[int], None] | None = None
        """Called with the step of every downlinked status (a mission script's timeline)."""
        self._lock = threading.Lock()
        self._file = open(self.received_path, "a")  # noqa: SIM115 -- closed in close()
        self._sent = open(sent_path, "a")  # noqa: SIM115 -- closed in close()
        self._uplink_log = open(cfg.out / "uplink.jsonl", "a")  # noqa: SIM115 -- close()
        connect_s = TLS_CONNECT_TIMEOUT_S if cfg.timeout_s <= 0 else \
            min(TLS_CONNECT_TIMEOUT_S, cfg.timeout_s)
        try:
            self.session = open_session(
                SessionConfig(mode="peer", connect=tuple(cfg.connect), namespace=cfg.namespace),
                tls=station_tls(cfg), connect_timeout_s=connect_s)
        except ConfigError as exc:
            self._close_files()
            if not any(e.startswith("tls/") for e in cfg.connect):
                raise
            raise ConfigError(
                f"no TLS link to the mission at {', '.join(cfg.connect)} within "
                f"{connect_s:g} s: connect by a name the rover's certificate holds "
                "(127.0.0.1, localhost, its host name, or a --rover-hosts name of `rovergate "
                "credentials`), with credentials from the same CA, to a mission that is "
                f"running ({str(exc).split(': ', 1)[-1][:200]})") from None
        self._ack = self.session.declare_publisher(
            self.keys.key("downlink_ack"), encoding=cdr_encoding("downlink_ack"),
            congestion_control=zenoh.CongestionControl.BLOCK)
        self._uplink = self.session.declare_publisher(
            self.keys.key("uplink"), encoding=cdr_encoding("uplink"),
            congestion_control=zenoh.CongestionControl.BLOCK)
        self._sub = self.session.declare_subscriber(self.keys.key("downlink"), self._on_frame)
        self._report_sub = self.session.declare_subscriber(self.keys.key("uplink_report"),
                                                           self._on_report)
        self.rover_seen = threading.Event()
        self.rover_gone = threading.Event()
        self._rover_sub = self.session.liveliness().declare_subscriber(
            self.keys.alive("rover"), self._on_rover, history=True)
        self._token = self.session.liveliness().declare_token(self.keys.alive("station"))

    @property
    def dictionary(self) -> Dictionary:
        """What may be sent: the rover's list once it came down, this installation's
        before."""
        return self.store.dictionary

    def _on_rover(self, sample: zenoh.Sample) -> None:
        if sample.kind == zenoh.SampleKind.PUT:
            self.rover_seen.set()
            self.store.rover_on_link = True
            self.log.info("the rover's mission manager is on the link")
        elif self.rover_seen.is_set():
            self.store.rover_on_link = False
            self.store.rover_left = True
            self.rover_gone.set()

    def _on_frame(self, sample: zenoh.Sample) -> None:
        try:
            _, frame = check_and_decode("downlink", sample)
        except MessageError as exc:
            self.dropped += 1
            self.log.warning("dropped a downlink frame: %s (%d dropped)", exc, self.dropped)
            return
        self._ack.put(encode("downlink_ack", DownlinkAck([frame.seq])))
        with self._lock:
            if frame.seq in self.seen:
                self.duplicates += 1
                return
            self.seen.add(frame.seq)
            self._record(frame)

    def _on_report(self, sample: zenoh.Sample) -> None:
        """The ground transmitter radiated a command."""
        try:
            _, report = check_and_decode("uplink_report", sample)
        except MessageError as exc:
            self.dropped += 1
            self.log.warning("dropped a transmitter report: %s (%d dropped)", exc,
                             self.dropped)
            return
        row = {"id": report.id, "verb": report.verb, "step": report.step,
               "arrives_s": report.received_s, "wall": time.time()}
        with self._lock:
            self._uplink_log.write(json.dumps(row) + "\n")
            self._uplink_log.flush()
        self.store.add_radiated(row)
        self.log.info("command %d (%s) radiated at link step %d; it reaches the rover at "
                      "t=%.0f s", report.id, report.verb, report.step, report.received_s)

    def _record(self, frame: TelemetryFrame) -> None:
        row: dict = {"seq": frame.seq, "kind": frame.kind, "step": frame.step,
                     "radiated_s": frame.radiated_s, "received_wall": time.time(),
                     "bytes": len(frame.payload)}
        try:
            value = decode_item(frame.kind, frame.msgtype, frame.payload)
        except MessageError as exc:
            self.log.warning("seq %d: %s", frame.seq, exc)
            row["error"] = str(exc)
        else:
            if isinstance(value, MissionStatus):
                row.update(state=value.state, coverage=value.coverage,
                           collisions=value.collisions, condition=value.condition,
                           steps_total=value.steps_total)
            elif isinstance(value, Pose):
                row.update(position=[float(v) for v in value.position], yaw=value.yaw)
            elif isinstance(value, MissionEvent):
                row.update(event=value.kind, detail=value.detail)
            elif isinstance(value, CommandAck):
                row.update(id=value.id, verb=value.verb, state=value.state,
                           executed_step=value.step, received_s=value.received_s,
                           detail=value.detail)
            elif isinstance(value, np.ndarray):
                np.save(self.cfg.out / "map_latest.npy", value)
                row.update(points=len(value))
        # On disk first: whoever reads the log line finds the row in received.jsonl.
        self._file.write(json.dumps(row) + "\n")
        self._file.flush()
        self.store.add_received(row)
        if isinstance(value, MissionStatus) and "error" not in row and \
                self.on_status is not None:
            self.on_status(value.step)
        if "error" not in row:
            self.log.info("seq %d %-11s step %3d  %s", frame.seq, frame.kind, frame.step,
                          summarize(frame.kind, value))

    def accept(self, line: str) -> GroundCommand:
        """A typed command, checked against the allowlist (:attr:`dictionary`), numbered and
        queued on the ground (sent.jsonl); CommandError says why one is refused (nothing is
        queued then). :meth:`transmit` sends it up."""
        with self._lock:
            command = read_command(line, self.next_id, self.dictionary)
            self.next_id += 1
            row = {"id": command.id, "verb": command.verb, "args": list(command.args),
                   "line": command_line(command), "sent_wall": time.time()}
            self._sent.write(json.dumps(row) + "\n")
            self._sent.flush()
        self.store.add_sent(row)
        return command

    def transmit(self, command: GroundCommand, give_up: Callable[[], bool] | None = None
                 ) -> bool:
        """Put an accepted command on the uplink once the mission manager's bridge listens
        (it radiates it in the next window); False when it was not (the bridge left, Ctrl-C,
        or ``give_up()`` said so first)."""
        # A put that no subscriber matches is lost: wait for the bridge to be on the link.
        while not self._uplink.matching_status.matching:
            if STOP.is_set() or self.rover_gone.is_set() or (give_up and give_up()):
                self.log.error("command %d not sent (%s): the mission's bridge is not on the "
                               "link", command.id, command_line(command))
                return False
            time.sleep(0.05)
        self._uplink.put(encode("uplink", command))
        self.log.info("command %d queued: %s (it goes up in the next contact window)",
                      command.id, command_line(command))
        return True

    def send(self, line: str, give_up: Callable[[], bool] | None = None
             ) -> GroundCommand | None:
        """:meth:`accept` and :meth:`transmit` a typed command; None when it was refused
        (the reason is logged) or not sent."""
        try:
            command = self.accept(line)
        except CommandError as exc:
            self.log.error("refused: %s", exc)
            return None
        return command if self.transmit(command, give_up) else None

    def _close_files(self) -> None:
        for f in (self._file, self._sent, self._uplink_log):
            f.close()

    def close(self) -> None:
        self._token.undeclare()
        self._rover_sub.undeclare()
        self._report_sub.undeclare()
        self._sub.undeclare()
        self.session.close()
        self._close_files()


def gaps(seqs: set[int]) -> list[int]:
    """Sequence numbers missing between the lowest and the highest received."""
    if not seqs:
        return []
    return sorted(set(range(min(seqs), max(seqs) + 1)) - seqs)


def console_config(cfg: GroundConfig) -> ConsoleConfig:
    """The console's part of the station's flags."""
    return ConsoleConfig(cfg.web_host, cfg.web_port, cfg.web_token_file, cfg.web_cert,
                         cfg.web_key, cfg.web_client_ca)


def check_sends(cfg: GroundConfig) -> None:
    """Every --send command, checked before anything starts: one the allowlist refuses is
    one line naming it and why (nothing is sent)."""
    dictionary = local_dictionary()
    for line in cfg.commands:
        try:
            read_command(line, 0, dictionary)
        except CommandError as exc:
            raise ConfigError(f"--send {line!r}: {exc}") from None


def main(cfg: GroundConfig) -> int:
    source = "--connect" if cfg.connect else str(Path(cfg.mission) / LINK_FILE)
    cfg = resolve_link(cfg)  # a LinkFileError is one line from the command line
    check_sends(cfg)
    console = None
    if cfg.web:
        check_web(console_config(cfg))  # e.g. beyond loopback without a token: one line
    log = init_logging("ground")
    station = GroundStation(cfg, log)
    log.info("ground station on %s (from %s, namespace %s); recording to %s",
             ", ".join(cfg.connect), source, cfg.namespace, cfg.out)
    deadline = time.monotonic() + cfg.timeout_s if cfg.timeout_s > 0 else None

    def out_of_time() -> bool:
        return deadline is not None and time.monotonic() > deadline

    # Commands are put on the uplink from this thread only, so that no thread still in
    # Zenoh outlives the session (that aborts the interpreter at exit): standard input's
    # reader and the console queue them here.
    outbox: queue.Queue[GroundCommand] = queue.Queue()
    typed: queue.Queue[str] = queue.Queue()
    try:
        if cfg.web:
            console = Console(station, console_config(cfg), outbox.put, log)
            console.start()
        for line in cfg.commands:
            command = station.send(line, give_up=out_of_time)
            if command is None and out_of_time():
                break
        if cfg.stdin and not sys.stdin.closed:
            def read_stdin() -> None:
                for line in sys.stdin:
                    if line.strip():
                        typed.put(line)
            threading.Thread(target=read_stdin, daemon=True).start()
        while not STOP.is_set():
            if cfg.until_mission_ends and station.rover_gone.is_set():
                log.info("the mission manager left the link"
                         + (f"; the console at {console.url} closes with the station (keep it "
                            "up with --no-until-mission-ends)" if console else ""))
                break
            if out_of_time():
                break
            with contextlib.suppress(queue.Empty):
                station.send(typed.get(timeout=0.05), give_up=out_of_time)
            with contextlib.suppress(queue.Empty):
                while True:
                    station.transmit(outbox.get_nowait(), give_up=out_of_time)
    finally:
        if console is not None:
            console.stop()
        station.close()
    missing = gaps(station.seen)
    log.info("received %d items (sequence %s), %d duplicates dropped, gaps: %s",
             len(station.seen),
             f"{min(station.seen)}..{max(station.seen)}" if station.seen else "none",
             station.duplicates, missing or "none")
    if not station.rover_seen.is_set() and not STOP.is_set():
        log.error("the mission at %s was never on the link in %g s (is it running, and does "
                  "this station have the link's credentials?)", ", ".join(cfg.connect),
                  cfg.timeout_s)
        return 1
    return 0
