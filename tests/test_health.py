"""Health: a module killed mid-mission is restarted, rebuilds its state from the mission's
journal, and the loop resumes at the same step with the same numbers."""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import zenoh

from mission.journal import Journal
from rovergate.messages import decode
from rovergate.session import SessionConfig, free_loopback_port, zenoh_config

ROVERGATE = [sys.executable, "-m", "mission.cli"]


def test_journal_keeps_every_step_of_replay_topics_and_the_last_of_bulky_ones():
    j = Journal(keep_last=2)
    for step in range(5):
        j.add("depth", step, bytes([step]))
        j.add("surface", step, bytes([step]))
    j.add("depth", 3, b"again")  # a redone step replaces the earlier sample
    assert [e.step for e in j.range("depth", 0, 4)] == [0, 1, 2, 3, 4]
    assert [e.payload for e in j.range("depth", 3, 3)] == [b"again"]
    assert [e.step for e in j.range("surface", 0, 4)] == [3, 4]
    assert list(j.range("depth", 7, 9)) == []


def _status_watcher(port: int, steps: list[int], stop: threading.Event) -> threading.Thread:
    def run() -> None:
        cfg = SessionConfig(mode="client", connect=(f"tcp/127.0.0.1:{port}",))
        deadline = time.monotonic() + 60
        session = None
        while session is None and not stop.is_set():
            try:
                session = zenoh.open(zenoh_config(cfg))
            except zenoh.ZError:
                assert time.monotonic() < deadline
                time.sleep(0.2)
        if session is None:
            return
        sub = session.declare_subscriber(
            "rover/mission/status",
            lambda s: steps.append(decode("status", s.payload.to_bytes())[0]))
        stop.wait()
        sub.undeclare()
        session.close()
    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    return thread


def test_killed_modules_restart_and_the_mission_ends_as_if_nothing_happened(tmp_path: Path):
    """Each module is SIGKILLed once at a different step; the mission completes, and its
    per-step coverage and gate counts equal an uninterrupted in-process run's exactly."""
    steps, condition = 12, "gated"
    port = free_loopback_port()
    mission = subprocess.Popen(
        [*ROVERGATE, "run", "--steps", str(steps), "--condition", condition, "--no-progress",
         "--out", str(tmp_path / "p"), "--listen", f"tcp/127.0.0.1:{port}"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    lines: list[str] = []
    reader = threading.Thread(target=lambda: lines.extend(mission.stderr), daemon=True)
    reader.start()
    seen: list[int] = []
    stop = threading.Event()
    watcher = _status_watcher(port, seen, stop)
    kills = {2: "sim", 4: "planner", 6: "mapper", 8: "gate"}
    killed: list[str] = []
    try:
        deadline = time.monotonic() + 300
        while kills and mission.poll() is None and time.monotonic() < deadline:
            step = max(seen, default=-1)
            if step in kills:
                name = kills.pop(step)
                # The most recent "started <name> (pid N)" line is the live process.
                pids = [int(m.group(1)) for line in list(lines)
                        if (m := re.search(rf"started {name} \(pid (\d+)\)", line))]
                os.kill(pids[-1], signal.SIGKILL)
                killed.append(name)
            time.sleep(0.02)
        assert mission.wait(300) == 0, "".join(lines)[-4000:]
    finally:
        stop.set()
        if mission.poll() is None:
            mission.kill()
        watcher.join(10)
        reader.join(10)
    assert killed == ["sim", "planner", "mapper", "gate"], (killed, seen)
    inproc = subprocess.run(
        [*ROVERGATE, "run", "--steps", str(steps), "--condition", condition, "--in-process",
         "--no-progress", "--out", str(tmp_path / "i")], capture_output=True, text=True,
        timeout=300)
    assert inproc.returncode == 0, inproc.stderr[-3000:]
    p = json.loads((tmp_path / "p" / "metrics.json").read_text())
    i = json.loads((tmp_path / "i" / "metrics.json").read_text())
    assert (tmp_path / "p" / "coverage.csv").read_text() == \
        (tmp_path / "i" / "coverage.csv").read_text()
    assert p["suppressed_per_step"] == i["suppressed_per_step"]
    assert [r["module"] for r in p["restarts"]] == killed
    for r in p["restarts"]:
        assert r["death_to_resume_s"] is not None and r["death_to_resume_s"] > 0, r
    for name in killed:
        log = (tmp_path / "p" / "logs" / f"{name}.log").read_text()
        assert "resumed at step" in log and "mission done" in log, name
