"""Mission scripts: a mission written as a TOML file, and the Python API that runs one.

A mission file holds the configuration as ``rovergate run`` takes it (top-level settings, and
one table per section: ``[scene]``, ``[contact]``, ``[planner]``, ...; the names of the flags,
with ``_`` for ``-``) and an operations timeline: ground commands, each sent by a ground
station at a given step or contact window through the mission's real uplink::

    steps = 40
    condition = "learned"

    [scene]
    name = "crater"

    [[timeline]]
    step = 6                      # once the ground has seen the rover reach step 6
    command = "set gate.k=3"

    [[timeline]]
    window = 2                    # when the second contact window opens
    command = "condition gated"

``rovergate run mission.toml [flags]`` runs it: flags given after the file override it. With
a timeline, the run makes fresh credentials for the link in ``OUT/credentials`` (unless the
file's ``[contact]`` names the rover's and its ``[ground]`` table the station's), so that the
uplink is mutual TLS, starts a ground station (:class:`mission.link.ground.GroundStation`) on the
mission's ground endpoint, and plays the timeline: a command goes up in the window it is
sent in (or the next), reaches the rover one light time later, runs at the next step
boundary and is acknowledged on the downlink. The station records everything under
``OUT/ground``; the mission's report lists the commands it executed (``metrics.json``,
``link.commands``).

``[ground]`` may also say ``web = true`` (and ``web_port``): the mission's ground station then
serves the operator's console on loopback (:mod:`mission.link.console`), timeline or not, and
the log names its address.

The ground sees the rover's step only from the downlinked status, so "at step N" means "once
the ground has received a status of step N or later". A window is numbered from 1 in the
mission's contact plan; the ground knows the plan, and sends the command once it receives
the first status of that window.

In Python::

    from mission import Mission
    mission = Mission.load("examples/mission.toml", steps=12, out="runs/script")
    mission.at_step(3, "set planner.n_candidates=24")
    result = mission.run()
    result.metrics["final_coverage"], result.acks
"""

from __future__ import annotations

import dataclasses
import json
import logging
import queue
import threading
import tomllib
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from rovergate.config import MissionConfig, from_dict
from rovergate.errors import ConfigError

log = logging.getLogger("rovergate.script")


@dataclass(frozen=True)
class TimelineEntry:
    """One ground command of the timeline: at a step (as the ground sees it) or when a
    contact window (numbered from 1) opens."""

    command: str
    step: int | None = None
    window: int | None = None

    def describe(self) -> str:
        when = f"step {self.step}" if self.step is not None else f"window {self.window}"
        return f"{when}: {self.command}"


@dataclass
class MissionScript:
    """A mission file, parsed: the configuration, the timeline, the station's credentials."""

    config: MissionConfig
    timeline: list[TimelineEntry] = field(default_factory=list)
    station_credentials: Path | None = None
    source: str = "<python>"
    web: bool = False
    """Serve the operator's console from the mission's ground station (on loopback)."""
    web_port: int = 0


#: What a mission file's [ground] table takes.
GROUND_KEYS = {"credentials": "the station's credentials directory, made by `rovergate "
               "credentials`", "web": "true: serve the operator's console on loopback",
               "web_port": "the console's port, 0 for a free one"}


# --- reading a mission file -------------------------------------------------------------------

def load_script(path: Path) -> MissionScript:
    """Read a mission file; a bad one raises ConfigError with one line naming the file, the
    key and how to fix it."""
    path = Path(path)
    try:
        data = tomllib.loads(path.read_text())
    except FileNotFoundError:
        raise ConfigError(f"mission file {path} does not exist; see examples/mission.toml"
                          ) from None
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"mission file {path} is not valid TOML: {exc}") from None
    return parse_script(data, str(path))


def parse_script(data: dict[str, Any], source: str = "<python>") -> MissionScript:
    data = dict(data)
    timeline_data = data.pop("timeline", [])
    ground = data.pop("ground", {})
    if not isinstance(ground, dict) or set(ground) - set(GROUND_KEYS):
        raise ConfigError(f"{source}: [ground] takes only " + ", ".join(
            f"`{k}` ({what})" for k, what in GROUND_KEYS.items()))
    web = ground.get("web", False)
    if not isinstance(web, bool):
        raise ConfigError(f"{source}: [ground] `web` must be true or false, got {web!r}")
    port = ground.get("web_port", 0)
    if not isinstance(port, int) or isinstance(port, bool) or not 0 <= port <= 65535:
        raise ConfigError(f"{source}: [ground] `web_port` must be a port, 0 (a free one) to "
                          f"65535, got {port!r}")
    _check_types(MissionConfig, data, source, "")
    try:
        config = from_dict(MissionConfig, data, source)
    except (ValueError, TypeError) as exc:
        raise ConfigError(f"{exc}; the keys are `rovergate run`'s flags (`--planner.name` is "
                          "`name` in [planner]); see `rovergate run --help`") from None
    if not isinstance(timeline_data, list):
        raise ConfigError(f"{source}: `timeline` must be an array of tables ([[timeline]])")
    timeline = [_entry(e, source, i, config) for i, e in enumerate(timeline_data)]
    station = Path(ground["credentials"]) if ground.get("credentials") else None
    return MissionScript(config, timeline, station, source, web, port)


def _entry(e: Any, source: str, i: int, config: MissionConfig) -> TimelineEntry:
    where = f"{source}: timeline entry {i + 1}"
    if not isinstance(e, dict) or set(e) - {"step", "window", "command"}:
        raise ConfigError(f"{where}: takes `command` and one of `step` or `window`")
    if not isinstance(e.get("command"), str):
        raise ConfigError(f"{where}: needs `command`, a ground command as `rovergate ground` "
                          "takes it (e.g. \"set gate.k=3\")")
    try:
        check_timeline_command(config, e["command"])
    except ValueError as exc:
        raise ConfigError(f"{where}: {e['command']!r} would be refused: {exc}") from None
    if ("step" in e) == ("window" in e):
        raise ConfigError(f"{where}: give exactly one of `step` (a planning step) or "
                          "`window` (a contact window, from 1)")
    value = e.get("step", e.get("window"))
    least = 0 if "step" in e else 1
    if not isinstance(value, int) or isinstance(value, bool) or value < least:
        raise ConfigError(f"{where}: `{'step' if 'step' in e else 'window'}` must be an "
                          f"integer of at least {least}, got {value!r}")
    return TimelineEntry(e["command"], step=e.get("step"), window=e.get("window"))


def check_timeline_command(config: MissionConfig, line: str) -> None:
    """A timeline command, held against the allowlist (:mod:`mission.link.commands`) with
    this mission's planners, and a ``set`` against the rover's own check of the values
    (:func:`mission.link.operations.apply_settings`): what the rover would refuse in flight
    is refused before anything starts (CommandError says why)."""
    from mission.link.commands import local_dictionary, read_command
    from mission.link.operations import apply_settings
    from rovergate.config import planner_programs
    command = read_command(line, 0, local_dictionary(tuple(planner_programs(config.planner)),
                                                     "mission"))
    if command.verb == "set":
        apply_settings(config, list(command.args))


def _check_types(cls: type, data: dict[str, Any], source: str, prefix: str) -> None:
    """A value of the wrong type is named before anything runs (TOML carries types)."""
    hints = typing.get_type_hints(cls, include_extras=True)
    fields = {f.name: f for f in dataclasses.fields(cls)}
    for key, value in data.items():
        if key not in fields:
            continue  # from_dict names it
        hint = hints[key]
        while typing.get_origin(hint) is typing.Annotated:
            hint = typing.get_args(hint)[0]
        name = f"{prefix}{key}"
        if dataclasses.is_dataclass(hint):
            if not isinstance(value, dict):
                raise ConfigError(f"{source}: `{name}` is a section; write it as a table "
                                  f"[{name}]")
            _check_types(hint, value, source, name + ".")
            continue
        want = _expected(hint)
        if want is not None and not want[0](value):
            raise ConfigError(f"{source}: `{name}` must be {want[1]}, got {value!r}")


def _expected(hint: Any):
    origin = typing.get_origin(hint)
    if hint is bool:
        return (lambda v: isinstance(v, bool)), "true or false"
    if hint is int:
        return (lambda v: isinstance(v, int) and not isinstance(v, bool)), "an integer"
    if hint is float:
        return (lambda v: isinstance(v, int | float) and not isinstance(v, bool)), "a number"
    if hint is str or hint is Path:
        return (lambda v: isinstance(v, str)), "a string"
    if hint == Path | None:
        return (lambda v: v is None or isinstance(v, str)), "a string (a path)"
    if origin is tuple:
        return (lambda v: isinstance(v, list)), "an array"
    if origin is typing.Literal:
        options = typing.get_args(hint)
        return (lambda v: v in options), "one of " + ", ".join(map(repr, options))
    return None


# --- running one --------------------------------------------------------------------------------

@dataclass
class MissionResult:
    """What a finished mission left in its directory."""

    out: Path
    metrics: dict[str, Any]
    acks: list[dict[str, Any]]
    """The command acknowledgements the ground station received (id, verb, state,
    executed_step)."""
    unsent: list[str]
    """Timeline entries the ground never sent (their step or window never came)."""

    @property
    def coverage(self) -> list[float]:
        return self.metrics["coverage"]

    @property
    def bag(self) -> Path | None:
        bag = self.out / "bag"
        return bag if bag.is_dir() else None

    @classmethod
    def read(cls, out: Path) -> MissionResult:
        """The record of the mission in ``out``."""
        out = Path(out)
        try:
            metrics = json.loads((out / "metrics.json").read_text())
        except FileNotFoundError:
            raise ConfigError(f"{out} holds no finished mission (no metrics.json)") from None
        acks = []
        received = out / "ground" / "received.jsonl"
        if received.exists():
            rows = [json.loads(line) for line in received.read_text().splitlines()]
            acks = [{k: r.get(k) for k in ("id", "verb", "state", "executed_step", "detail")}
                    for r in rows if r.get("kind") == "command_ack"]
        unsent_file = out / "ground" / "unsent.json"
        unsent = json.loads(unsent_file.read_text()) if unsent_file.exists() else []
        return cls(out, metrics, acks, unsent)


class Mission:
    """A mission to configure and run from Python: the configuration (:attr:`config`, a
    :class:`rovergate.config.MissionConfig`) and the timeline of ground commands."""

    def __init__(self, config: MissionConfig | None = None, **settings: Any) -> None:
        """``settings``: top-level settings and sections as a mission file writes them
        (``Mission(steps=20, scene={"name": "crater"})``), over ``config``."""
        base = config if config is not None else MissionConfig()
        self.script = MissionScript(base)
        if settings:
            self.configure(**settings)

    @classmethod
    def load(cls, path: Path | str, **settings: Any) -> Mission:
        """A mission file, with ``settings`` over it."""
        mission = cls()
        mission.script = load_script(Path(path))
        if settings:
            mission.configure(**settings)
        return mission

    @property
    def config(self) -> MissionConfig:
        return self.script.config

    @property
    def timeline(self) -> list[TimelineEntry]:
        return self.script.timeline

    def configure(self, **settings: Any) -> Mission:
        """Set top-level settings or sections' fields (a dict per section)."""
        from rovergate.config import to_dict
        merged = to_dict(self.config)
        for key, value in settings.items():
            if isinstance(value, Path):
                value = str(value)
            if isinstance(value, dict) and isinstance(merged.get(key), dict):
                merged[key] = {**merged[key], **value}
            else:
                merged[key] = value
        self.script = dataclasses.replace(
            self.script, config=parse_script(merged, self.script.source).config)
        return self

    def at_step(self, step: int, command: str) -> Mission:
        """Send ``command`` once the ground has seen the rover reach ``step``."""
        self.script.timeline.append(_entry({"step": step, "command": command},
                                           self.script.source, len(self.timeline), self.config))
        return self

    def at_window(self, window: int, command: str) -> Mission:
        """Send ``command`` when contact window ``window`` (from 1) opens."""
        self.script.timeline.append(_entry({"window": window, "command": command},
                                           self.script.source, len(self.timeline), self.config))
        return self

    def run(self, progress: bool = False) -> MissionResult:
        """Launch the process set, play the timeline, write the report; the record.
        Raises :class:`rovergate.errors.MissionFailed` when the mission fails."""
        from rovergate.errors import MissionFailed
        cfg = dataclasses.replace(self.config, progress=progress)
        code = run_script(dataclasses.replace(self.script, config=cfg))
        if code != 0:
            raise MissionFailed(f"the mission in {cfg.out} failed (exit code {code}); see "
                                f"{Path(cfg.out) / 'logs'}")
        return MissionResult.read(Path(cfg.out))


def run_script(script: MissionScript) -> int:
    """Run a mission script: the mission, and with a timeline the ground station that plays
    it over the authenticated uplink. Returns the mission's exit code."""
    from mission.run import main as run_main
    cfg = script.config
    if not script.timeline and not script.web:
        return run_main(cfg)
    if cfg.in_process:
        raise ConfigError(f"{script.source}: a timeline goes through the ground link, which "
                          "only the process set has; leave out --in-process")
    if cfg.resume:
        raise ConfigError(f"{script.source}: a timeline is not resumed (its commands that "
                          "ran would go up again); resume with `rovergate run --out OUT "
                          "--resume` and send what is left with `rovergate ground`")
    if not cfg.contact.enabled:
        raise ConfigError(f"{script.source}: a timeline needs the link to the ground; leave "
                          "contact.enabled at true")
    out = Path(cfg.out)
    _check_timeline(cfg, script)
    cfg, station_credentials = _credentials(cfg, script, out)
    player = TimelinePlayer(cfg, script.timeline, station_credentials, out,
                            web_port=script.web_port if script.web else None)
    try:
        return run_main(cfg, on_link=player.start)
    finally:
        player.stop()


def _credentials(cfg: MissionConfig, script: MissionScript, out: Path
                 ) -> tuple[MissionConfig, Path]:
    """The rover's and the station's credentials: the script's, or fresh ones for this run."""
    if cfg.contact.credentials is not None:
        if script.station_credentials is None:
            raise ConfigError(f"{script.source}: [contact] names the rover's credentials; name "
                              "the station's too: [ground] credentials = \"DIR/station\"")
        return cfg, script.station_credentials
    from mission.link.credentials import CredentialsConfig, create
    root = out / "credentials"
    made = {name: root / name for name in ("ca", "rover", "station")}
    if all(d.is_dir() for d in made.values()):
        # This directory's own, from an earlier run of a script (a mission may be using
        # them now): used again, never overwritten.
        log.info("the timeline's uplink is mutual TLS with the credentials in %s", root)
    else:
        made = create(CredentialsConfig(out=root, station_name=cfg.contact.ground_stations[0]))
        log.info("the timeline's uplink is mutual TLS with fresh credentials in %s", root)
    contact = dataclasses.replace(cfg.contact, credentials=made["rover"])
    return dataclasses.replace(cfg, contact=contact), made["station"]


def _check_timeline(cfg: MissionConfig, script: MissionScript) -> None:
    from mission.link.contact import ContactPlan
    windows = ContactPlan(cfg.contact).windows_between(0, cfg.steps)
    for e in script.timeline:
        try:  # again with the flags given after the file
            check_timeline_command(cfg, e.command)
        except ValueError as exc:
            raise ConfigError(f"{script.source}: timeline {e.describe()} would be refused: "
                              f"{exc}") from None
        if e.step is not None and e.step > cfg.steps:
            raise ConfigError(f"{script.source}: timeline {e.describe()} is after the "
                              f"mission's last step ({cfg.steps})")
        if e.window is not None and e.window > len(windows):
            raise ConfigError(f"{script.source}: timeline {e.describe()}: the contact plan "
                              f"has {len(windows)} windows in {cfg.steps} steps")


class TimelinePlayer:
    """The ground side of a script: a ground station on the mission's link that sends each
    timeline command when its step or window comes (as the downlinked status shows)."""

    def __init__(self, cfg: MissionConfig, timeline: list[TimelineEntry],
                 credentials: Path, out: Path, web_port: int | None = None) -> None:
        from mission.link.contact import ContactPlan
        self.cfg = cfg
        self.web_port = web_port
        self.console: Any = None
        self.credentials = credentials
        self.out = out
        windows = ContactPlan(cfg.contact).windows_between(0, cfg.steps)
        # Each entry's trigger as a step the ground must have seen.
        self.pending = sorted(
            ((e.step if e.step is not None else windows[e.window - 1][0]), i, e)
            for i, e in enumerate(timeline))
        self.station = None
        self._seen_step = -1
        self._cv = threading.Condition()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._uplink_thread: threading.Thread | None = None
        self._outbox: queue.Queue[Any] = queue.Queue()

    def start(self) -> None:
        """Called once the mission's ground endpoint is up (its ground.json written)."""
        from mission.link.ground import GroundConfig, GroundStation, resolve_link
        gcfg = resolve_link(GroundConfig(mission=self.out, credentials=self.credentials,
                                         out=self.out / "ground", stdin=False))
        self.station = GroundStation(gcfg, logging.getLogger("rovergate.ground"))
        self.station.on_status = self._on_status
        self._thread = threading.Thread(target=self._play, name="timeline", daemon=True)
        self._thread.start()
        if self.web_port is not None:
            from mission.link.console import Console, ConsoleConfig
            self._uplink_thread = threading.Thread(target=self._uplink, name="console-uplink",
                                                   daemon=True)
            self._uplink_thread.start()
            self.console = Console(self.station, ConsoleConfig(port=self.web_port),
                                   self._outbox.put, logging.getLogger("rovergate.ground"))
            self.console.start()

    def _uplink(self) -> None:
        """Put the console's commands on the uplink (a thread of its own: the timeline's
        waits on the ground's picture of the rover)."""
        while not self._stop.is_set():
            try:
                command = self._outbox.get(timeout=0.1)
            except queue.Empty:
                continue
            self.station.transmit(command, give_up=self._stop.is_set)

    def _on_status(self, step: int) -> None:
        with self._cv:
            self._seen_step = max(self._seen_step, step)
            self._cv.notify_all()

    def _play(self) -> None:
        while self.pending and not self._stop.is_set():
            due, _, entry = self.pending[0]
            with self._cv:
                self._cv.wait_for(lambda due=due: self._seen_step >= due
                                  or self._stop.is_set())
            if self._stop.is_set():
                break
            log.info("timeline %s (the ground saw step %d)", entry.describe(), self._seen_step)
            if self.station.send(entry.command, give_up=self._stop.is_set) is None:
                break  # not sent: it stays pending, and unsent.json lists it
            self.pending.pop(0)

    def stop(self) -> None:
        self._stop.set()
        with self._cv:
            self._cv.notify_all()
        if self.console is not None:
            self.console.stop()
        for thread in (self._thread, self._uplink_thread):
            if thread is not None:
                thread.join(30)
        if self.station is None:
            return  # the mission ended before its link came up: nothing was played
        self.station.close()
        unsent = [e.describe() for _, _, e in self.pending]
        if unsent:
            log.warning("timeline entries never sent (their step or window did not come): %s",
                        "; ".join(unsent))
        (self.out / "ground").mkdir(parents=True, exist_ok=True)
        (self.out / "ground" / "unsent.json").write_text(json.dumps(unsent) + "\n")
