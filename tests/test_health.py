"""Health: a module killed mid-mission is restarted, rebuilds its state from the mission's
journal, and the loop resumes at the same step with the same numbers."""

from __future__ import annotations

import json
import os
import signal
from pathlib import Path

import pytest
from conftest import StatusWatcher, run_cli

from mission.journal import Journal
from rovergate.session import free_loopback_port


def test_journal_keeps_every_step_of_replay_topics_and_the_last_of_bulky_ones():
    j = Journal(keep_last=2)
    for step in range(5):
        j.add("depth", step, bytes([step]))
        j.add("surface", step, bytes([step]))
    # A redone step sends the same bytes; anything else later for a recorded step (a forged
    # sample) is not what the mission ran on: the first is kept.
    j.add("depth", 3, b"forged")
    assert [e.step for e in j.range("depth", 0, 4)] == [0, 1, 2, 3, 4]
    assert [e.payload for e in j.range("depth", 3, 3)] == [bytes([3])]
    assert [e.step for e in j.range("surface", 0, 4)] == [3, 4]
    assert list(j.range("depth", 7, 9)) == []


@pytest.mark.e2e
def test_killed_modules_restart_and_the_mission_ends_as_if_nothing_happened(tmp_path: Path,
                                                                          launch):
    """Each module is SIGKILLed once at a different step; the mission completes, and its
    per-step coverage and gate counts equal an uninterrupted in-process run's exactly."""
    steps, condition = 12, "gated"
    port = free_loopback_port()
    mission = launch("run", "--steps", str(steps), "--condition", condition,
                     "--out", str(tmp_path / "p"), "--listen", f"tcp/127.0.0.1:{port}")
    # The mission's session listens before it starts any module.
    mission.wait_for_line(r"started sim \(pid")
    watcher = StatusWatcher(port)
    kills = {2: "sim", 4: "planner", 6: "mapper", 8: "gate"}
    killed: list[str] = []
    try:
        for step, name in kills.items():
            watcher.wait_step(step)
            os.kill(mission.pid(name), signal.SIGKILL)
            killed.append(name)
        assert mission.finish(300) == 0, mission.text[-4000:]
    finally:
        watcher.close()
    assert killed == ["sim", "planner", "mapper", "gate"], (killed, watcher.steps)
    inproc = run_cli("run", "--steps", str(steps), "--condition", condition, "--in-process",
                     "--out", str(tmp_path / "i"), timeout=300)
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
