"""Shared fixtures: small missions, loopback Zenoh sessions (scouting off), and the one way
tests start process sets (:func:`launch`): every port free, every wait event-driven with a
deadline that says what it awaited, nothing left running."""

from __future__ import annotations

import dataclasses
import json
import re
import subprocess
import sys
import threading
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest
import zenoh

from mission.link.bridge import LINK_FILE
from rover_sim.catalog import load_scene, resolve_scene
from rovergate.config import MissionConfig, SessionConfig
from rovergate.session import free_loopback_port, zenoh_config

#: The command line, as users type it (the mission launches its modules the same way).
ROVERGATE = [sys.executable, "-m", "mission.cli"]


@pytest.fixture(scope="session")
def scene():
    return load_scene("arch_field")


def small_config(tmp_path: Path, **overrides) -> MissionConfig:
    cfg = MissionConfig(out=tmp_path / "run", progress=False, **overrides)
    cfg = dataclasses.replace(cfg, ready_timeout_s=90.0, step_timeout_s=90.0)
    resolve_scene(cfg.scene)
    return cfg


@pytest.fixture
def loopback_pair():
    """Two peer sessions linked over an explicit loopback endpoint, scouting off."""
    endpoint = f"tcp/127.0.0.1:{free_loopback_port()}"
    a = zenoh.open(zenoh_config(SessionConfig(listen=(endpoint,))))
    b = zenoh.open(zenoh_config(SessionConfig(connect=(endpoint,))))
    yield endpoint, a, b
    b.close()
    a.close()


def read_metrics(out: Path) -> dict:
    return json.loads((out / "metrics.json").read_text())


def run_cli(*args: str, timeout: float = 240) -> subprocess.CompletedProcess:
    """``rovergate ARGS --no-progress`` to completion."""
    return subprocess.run([*ROVERGATE, *args, "--no-progress"], capture_output=True, text=True,
                          timeout=timeout)


def recorded_mission(out: Path, steps: int, *flags: str) -> Path:
    """An in-process mission of ``steps`` steps in ``out`` (recorded, as every mission is);
    returns its bag's directory."""
    r = run_cli("run", "--in-process", "--steps", str(steps), "--out", str(out), *flags)
    assert r.returncode == 0, r.stderr[-3000:]
    return out / "bag"


class Waiter:
    """A condition that callbacks notify and a test waits on, with a deadline that says what
    it awaited (never a fixed sleep)."""

    def __init__(self) -> None:
        self.cv = threading.Condition()

    def notify(self) -> None:
        with self.cv:
            self.cv.notify_all()

    def wait_for(self, predicate: Callable[[], object], timeout_s: float, what: str,
                 detail: Callable[[], str] = lambda: "") -> object:
        with self.cv:
            value = self.cv.wait_for(predicate, timeout_s)
        if not value:
            raise AssertionError(f"no {what} within {timeout_s:.0f} s{detail()}")
        return value


class RovergateProcess:
    """A ``rovergate ...`` process whose stderr is read line by line as it comes."""

    def __init__(self, args: list[str], stdin: bool = False, new_session: bool = False
                 ) -> None:
        self.args = args
        self.proc = subprocess.Popen([*ROVERGATE, *args], stdout=subprocess.PIPE,
                                     stderr=subprocess.PIPE, text=True,
                                     stdin=subprocess.PIPE if stdin else subprocess.DEVNULL,
                                     start_new_session=new_session)
        self.lines: list[str] = []
        self.waiter = Waiter()
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        for line in self.proc.stderr:
            with self.waiter.cv:
                self.lines.append(line)
                self.waiter.cv.notify_all()
        with self.waiter.cv:
            self.lines.append("")  # end of stream
            self.waiter.cv.notify_all()

    @property
    def text(self) -> str:
        return "".join(self.lines)

    def _tail(self) -> str:
        return "; its stderr ends:\n" + "".join(self.lines[-30:])

    def wait_for_lines(self, pattern: str, count: int, timeout_s: float = 240) -> list[str]:
        """The first ``count`` stderr lines matching ``pattern``, waiting for them."""
        def state() -> list[str] | str | None:
            hits = [line for line in self.lines if re.search(pattern, line)]
            if len(hits) >= count:
                return hits[:count]
            return "ended" if self.lines[-1:] == [""] else None
        result = self.waiter.wait_for(state, timeout_s, f"{count} lines /{pattern}/",
                                      self._tail)
        if result == "ended":
            raise AssertionError(f"rovergate exited before {count} lines /{pattern}/"
                                 f"{self._tail()}")
        return result

    def wait_for_line(self, pattern: str, timeout_s: float = 120) -> re.Match:
        """The first stderr line matching ``pattern`` (a regex), waiting for it."""
        return re.search(pattern, self.wait_for_lines(pattern, 1, timeout_s)[0])

    def send(self, line: str) -> None:
        """Type a line on the process's standard input."""
        self.proc.stdin.write(line + "\n")
        self.proc.stdin.flush()

    def pid(self, module: str) -> int:
        """The pid of the live ``module`` process (from the latest "started" line)."""
        self.wait_for_line(rf"started {module} \(pid \d+\)")
        with self.waiter.cv:
            pids = [int(m.group(1)) for line in self.lines
                    if (m := re.search(rf"started {module} \(pid (\d+)\)", line))]
        return pids[-1]

    def finish(self, timeout_s: float = 240) -> int:
        """Wait for the process to exit; its exit code."""
        code = self.proc.wait(timeout_s)
        self._reader.join(10)
        return code

    def kill(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait(30)


def wait_gone(pid: int, timeout_s: float) -> bool:
    """Wait for process ``pid`` (not necessarily our child) to exit: True once it has, False
    when it is still there after ``timeout_s``. Event-driven, through a pidfd."""
    import os
    import select
    try:
        fd = os.pidfd_open(pid)
    except ProcessLookupError:
        return True
    try:
        return bool(select.select([fd], [], [], timeout_s)[0])
    finally:
        os.close(fd)


@pytest.fixture
def launch() -> Iterator[Callable[..., RovergateProcess]]:
    """Start ``rovergate`` processes (``launch("run", "--steps", "5", ...)``); any still
    running at the end of the test is killed."""
    started: list[RovergateProcess] = []

    def start(*args: str, stdin: bool = False, new_session: bool = False) -> RovergateProcess:
        flags = [*args, "--no-progress"] if args and args[0] in ("run", "study") else list(args)
        m = RovergateProcess(flags, stdin=stdin, new_session=new_session)
        started.append(m)
        return m
    yield start
    for m in started:
        m.kill()


class StatusWatcher:
    """A client session on a mission's ``--listen`` endpoint that records the steps of the
    mission clock's ticks."""

    def __init__(self, port: int) -> None:
        from rovergate.messages import decode
        self.steps: list[int] = []
        self.states: list[str] = []
        self.waiter = Waiter()
        self.session = zenoh.open(zenoh_config(SessionConfig(
            mode="client", connect=(f"tcp/127.0.0.1:{port}",))))

        def on_status(sample: zenoh.Sample) -> None:
            step, status = decode("status", sample.payload.to_bytes())
            with self.waiter.cv:
                self.steps.append(step)
                self.states.append(status.state)
                self.waiter.cv.notify_all()
        self._sub = self.session.declare_subscriber("rover/mission/status", on_status)

    def wait_step(self, step: int, timeout_s: float = 120) -> None:
        self.waiter.wait_for(lambda: self.steps and max(self.steps) >= step, timeout_s,
                             f"tick of step {step}")

    def close(self) -> None:
        self._sub.undeclare()
        self.session.close()


class LinkedMission:
    """A process-set mission with a ground station beside it (found through OUT/ground.json)
    on the authenticated link (mutual TLS, credentials made for the test), and the mission
    clock's ticks."""

    def __init__(self, tmp_path: Path, *flags: str, steps: int,
                 ground_flags: tuple[str, ...] = ()) -> None:
        from mission.link.credentials import CredentialsConfig, create
        self.port = free_loopback_port()
        self.out, self.ground_out = tmp_path / "m", tmp_path / "g"
        self.credentials = create(CredentialsConfig(out=tmp_path / "credentials"))
        # The ground link takes a free port of its own and says which in OUT/ground.json.
        self.mission = RovergateProcess(["run", "--steps", str(steps), "--no-progress", "--out",
                                str(self.out), "--listen", f"tcp/127.0.0.1:{self.port}",
                                "--contact.credentials", str(self.credentials["rover"]), *flags])
        self.ground: RovergateProcess | None = None
        self.watcher: StatusWatcher | None = None
        try:
            # Logged once OUT/ground.json is written.
            line = self.mission.wait_for_line("link to the ground on").string
            link = json.loads((self.out / LINK_FILE).read_text())
            assert link["pid"] == self.mission.proc.pid and \
                link["ground_namespace"] == "ground" and link["rover_namespace"] == "rover", link
            assert f"link to the ground on {link['listen'][0]} " in line
            assert link["endpoints"][0].startswith("tls/127.0.0.1:"), link
            self.watcher = StatusWatcher(self.port)
            self.ground = RovergateProcess(["ground", "--mission", str(self.out), "--out",
                                   str(self.ground_out), "--credentials",
                                   str(self.credentials["station"]), *ground_flags],
                                           stdin=True)
        except BaseException:
            self.close()
            raise

    @property
    def steps(self) -> list[int]:
        return self.watcher.steps

    def wait_step(self, step: int, timeout_s: float = 240) -> int:
        self.watcher.wait_step(step, timeout_s)
        return max(self.watcher.steps)

    def command(self, line: str) -> None:
        self.ground.send(line)

    def wait_for_row(self, pattern: str, pred, timeout_s: float = 240) -> dict:
        """The first row of the station's received.jsonl matching ``pred``, once the station
        has logged a line matching ``pattern`` (it logs a row after writing it)."""
        self.ground.wait_for_line(pattern, timeout_s)
        rows = [json.loads(line) for line in
                (self.ground_out / "received.jsonl").read_text().splitlines()]
        return next(r for r in rows if pred(r))

    def close(self) -> None:
        if self.watcher is not None:
            self.watcher.close()
        for m in (self.mission, self.ground):
            if m is not None:
                m.kill()

    def finish(self, timeout_s: float = 300) -> tuple[dict, list[dict], str]:
        try:
            assert self.mission.finish(timeout_s) == 0, self.mission.text[-4000:]
            self.ground.proc.stdin.close()
            assert self.ground.finish(60) == 0, self.ground.text[-3000:]
        finally:
            self.close()
        assert not (self.out / LINK_FILE).exists()  # the link is down: its file has gone
        metrics = json.loads((self.out / "metrics.json").read_text())
        rows = [json.loads(line) for line in
                (self.ground_out / "received.jsonl").read_text().splitlines()]
        return metrics, rows, self.ground.text
