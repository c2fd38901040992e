"""Health: a module killed mid-mission is restarted, rebuilds its state from the mission's
journal, and the loop resumes at the same step with the same numbers."""

from __future__ import annotations

import json
import os
import signal
from pathlib import Path

import pytest
from conftest import StatusWatcher, run_cli, wait_gone

from mission.runtime.journal import Journal
from rovergate.errors import ConfigError
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


def test_a_journal_with_a_file_holds_every_steps_samples_there_not_in_memory(tmp_path: Path):
    # 300 steps of a 100 kB depth image: 30 MB served, while the journal's memory stays
    # flat (a 2,000-step mission journals some 350 MB of such samples).
    import tracemalloc
    j = Journal(keep_last=2, path=tmp_path / "journal.sqlite")
    tracemalloc.start()
    try:
        for step in range(300):
            j.add("depth", step, bytes([step % 256]) * 100_000)
        held, _ = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert held < 2_000_000, held
    served = list(j.range("depth", 0, 299))
    assert [e.step for e in served] == list(range(300))
    assert all(e.payload == bytes([e.step % 256]) * 100_000 for e in served)
    assert j.nbytes() == 300 * 100_000
    j.close()


def test_the_journal_file_holds_what_the_journal_held(tmp_path: Path):
    """Written through as samples come: a journal opened again on the file (a restarted
    mission manager's) serves the same samples, bulky topics trimmed as in memory."""
    j = Journal(keep_last=2, path=tmp_path / "journal.sqlite")
    for step in range(5):
        j.add("depth", step, bytes([step]))
        j.add("surface", step, bytes([step]))
    j.add("depth", 3, b"forged")
    # Not closed: a killed manager does not close it either.
    again = Journal(keep_last=2, path=tmp_path / "journal.sqlite")
    for topic in ("depth", "surface"):
        assert list(again.range(topic, 0, 9)) == list(j.range(topic, 0, 9))
    assert again.steps("surface") == [3, 4]
    j.close()
    again.close()
    (tmp_path / "bad.sqlite").write_bytes(b"not a database at all" * 100)
    with pytest.raises(ConfigError, match="not a usable SQLite file"):
        Journal(path=tmp_path / "bad.sqlite")


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


@pytest.mark.e2e
def test_a_killed_mission_manager_resumes_and_ends_as_if_nothing_happened(tmp_path: Path,
                                                                         launch):
    """The mission manager is SIGKILLed in the middle of a mission, with a ground station on
    its authenticated link; its modules stop; ``rovergate run --out OUT --resume`` carries on
    from the checkpoint: the per-step coverage equals an uninterrupted run's exactly, and a
    station on the resumed link receives the telemetry numbered on, without a gap."""
    from mission.link.credentials import CredentialsConfig, create
    from mission.link.ground import gaps

    steps, condition, out, ground = 30, "gated", tmp_path / "p", tmp_path / "g"
    creds = create(CredentialsConfig(out=tmp_path / "credentials"))
    port = free_loopback_port()
    mission = launch("run", "--steps", str(steps), "--condition", condition, "--out", str(out),
                     "--listen", f"tcp/127.0.0.1:{port}", "--contact.credentials",
                     str(creds["rover"]), "--contact.windows", f"0+{steps}",
                     "--contact.light-time-s", "0")
    mission.wait_for_line("link to the ground on")
    station = ["ground", "--mission", str(out), "--out", str(ground), "--credentials",
               str(creds["station"]), "--no-stdin"]
    first = launch(*station)
    # The directory is the running manager's: neither a resume nor another mission in it.
    busy = run_cli("run", "--out", str(out), "--resume")
    assert busy.returncode == 2 and "another mission manager (pid " in busy.stderr, busy.stderr
    modules = {name: mission.pid(name) for name in ("sim", "mapper", "gate", "planner")}
    watcher = StatusWatcher(port)
    try:
        watcher.wait_step(10)
        os.kill(mission.proc.pid, signal.SIGKILL)
    finally:
        watcher.close()
    assert mission.finish(30) == -signal.SIGKILL
    for name, pid in modules.items():  # they notice the manager's token vanish, and stop
        assert wait_gone(pid, 60), f"{name} (pid {pid}) still runs without its mission"
    assert first.finish(60) == 0, first.text[-3000:]  # the rover left its link
    assert not (out / "metrics.json").exists()
    resumed = launch("run", "--out", str(out), "--resume")
    resumed.wait_for_line("link to the ground on")
    second = launch(*station)
    assert resumed.finish(300) == 0, resumed.text[-4000:]
    assert second.finish(60) == 0, second.text[-3000:]
    at = int(resumed.wait_for_line(r"resumed at step (\d+)").group(1))
    assert 1 <= at <= steps, at
    inproc = run_cli("run", "--steps", str(steps), "--condition", condition, "--in-process",
                     "--out", str(tmp_path / "i"), timeout=300)
    assert inproc.returncode == 0, inproc.stderr[-3000:]
    assert (out / "coverage.csv").read_text() == (tmp_path / "i" / "coverage.csv").read_text()
    p = json.loads((out / "metrics.json").read_text())
    i = json.loads((tmp_path / "i" / "metrics.json").read_text())
    assert p["suppressed_per_step"] == i["suppressed_per_step"]
    assert [r["step"] for r in p["manager_resumes"]] == [at]
    rows = [json.loads(line) for line in (ground / "received.jsonl").read_text().splitlines()]
    seqs = [r["seq"] for r in rows]
    assert len(seqs) == len(set(seqs)) and gaps(set(seqs)) == [] and min(seqs) == 1, seqs
    events = [r["event"] for r in rows if r["kind"] == "event"]
    assert events[0] == "mission-started" and "mission-resumed" in events
    assert events[-1] == "mission-done" and p["link"]["undelivered"] == 0
    assert not (out / "checkpoint.sqlite").exists()  # the mission ended: nothing to resume
    again = run_cli("run", "--out", str(out), "--resume")
    assert again.returncode == 2 and "does not exist" in again.stderr, again.stderr


def test_one_mission_manager_per_directory(tmp_path: Path):
    from mission.run import hold_directory
    held = hold_directory(tmp_path)
    with pytest.raises(ConfigError, match=rf"another mission manager \(pid {os.getpid()}\)"):
        hold_directory(tmp_path)
    held.close()  # as the kernel does when its process ends, SIGKILL included
    hold_directory(tmp_path).close()


def test_resume_takes_only_the_mission_directory(tmp_path: Path):
    r = run_cli("run", "--out", str(tmp_path), "--resume", "--steps", "5")
    assert r.returncode == 2
    assert r.stderr.strip().splitlines()[-1].endswith("leave out --steps"), r.stderr


def test_a_checkpoint_that_names_code_is_refused_not_run(tmp_path: Path):
    """The checkpoint is a pickle: one that would call a function when loaded is refused."""
    import pickle

    from mission.runtime.checkpoint import CHECKPOINT, load
    from rovergate.errors import ConfigError

    marker = tmp_path / "ran"

    class Exploit:
        def __reduce__(self):
            return (os.system, (f"touch {marker}",))

    def short(text: str) -> bytes:
        return b"\x8c" + bytes([len(text)]) + text.encode()
    # Pickle resolves dotted names: a module of ours and `subprocess.Popen` reach Popen.
    dotted = (b"\x80\x04" + short("mission.runtime.supervisor") + short("subprocess.Popen")
              + b"\x93"
              + short("touch") + short(str(marker)) + b"\x86\x85R.")
    good = pickle.dumps({}, protocol=pickle.HIGHEST_PROTOCOL)
    for state, appended in [(pickle.dumps(Exploit()), good), (dotted, good),
                            (b"\x80\x05garbage", good)]:
        write_checkpoint(tmp_path, state, appended)
        with pytest.raises(ConfigError, match="not a rovergate checkpoint"):
            load(tmp_path)
        assert not marker.exists()
    (tmp_path / CHECKPOINT).unlink()
    (tmp_path / CHECKPOINT).write_bytes(b"SQLite format 3\x00 but not really")
    with pytest.raises(ConfigError, match="not a rovergate checkpoint"):
        load(tmp_path)


def write_checkpoint(out: Path, state: bytes, appended: bytes) -> None:
    """A checkpoint file with these rows, as a forger would write it."""
    import sqlite3

    from mission.runtime.checkpoint import _SCHEMA, CHECKPOINT
    (out / CHECKPOINT).unlink(missing_ok=True)
    db = sqlite3.connect(out / CHECKPOINT)
    db.executescript(_SCHEMA)
    db.execute("INSERT INTO state VALUES (1, 1, ?)", (state,))
    db.execute("INSERT INTO appended (step, blob) VALUES (1, ?)", (appended,))
    db.commit()
    db.close()


def test_the_checkpoint_costs_the_same_at_every_step_and_reads_back_whole(tmp_path: Path):
    """Append only: each step writes what it appended and the rest, which does not grow, so
    the bytes a step costs at step 400 are those of step 40; loaded at any step, the state
    equals the one saved."""
    import dataclasses

    import numpy as np

    from mission.runtime.checkpoint import CheckpointWriter, LoopState, load
    from mission.scoring.record import MissionRecord
    from rovergate.config import MissionConfig
    from rovergate.types import ExecutionReport, PlanPath, Pose, StepTiming

    record = MissionRecord()
    state = LoopState(0, record, 0, None, "obs", MissionConfig(), None, {"timings": []})
    writer = CheckpointWriter(tmp_path)
    costs = []
    rng = np.random.default_rng(0)
    for t in range(400):
        record.coverage.append(float(rng.random()))
        record.base_xy.append((float(t), 0.5))
        record.paths.append(PlanPath(t, [Pose(rng.random(3), np.array([0, 0, 0, 1.0]))]))
        record.executions.append(ExecutionReport(t, False, 0, 1.5, 0.4, 1.0))
        record.add_stage("plan", 0.01 * t)
        state.transport["timings"].append(StepTiming(t, "plan", 0.01, 0))
        state = dataclasses.replace(state, step=t + 1)
        writer.save(state)
        costs.append(writer.bytes_written)
        if t in (3, 250, 399):
            back = load(tmp_path)
            assert back.step == t + 1 and back.record.coverage == record.coverage
            assert back.record.stage_s == record.stage_s and len(back.record.paths) == t + 1
            assert np.array_equal(back.record.paths[-1].poses[0].position,
                                  record.paths[-1].poses[0].position)
            assert back.transport["timings"] == state.transport["timings"]
    writer.close()
    assert np.median(costs[380:]) <= 1.05 * np.median(costs[30:50]), (costs[30:50], costs[380:])
    # Carried on after a resume: the new writer appends where the old one stopped.
    resumed = load(tmp_path)
    writer = CheckpointWriter(tmp_path, resumed)
    resumed.record.coverage.append(0.5)
    writer.save(dataclasses.replace(resumed, step=401))
    writer.close()
    assert load(tmp_path).record.coverage == [*record.coverage, 0.5]


def test_the_launcher_forks_modules_that_report_their_exit_like_processes(tmp_path: Path):
    """The module launcher (mission/runtime/launcher.py) forks a module from its preloaded
    interpreter: the module logs to its own file under its own command line, and its exit,
    by code or by signal, reaches the mission as subprocess.Popen.returncode gives it."""
    import dataclasses
    import subprocess

    from mission.runtime.launcher import Launcher
    from rovergate.config import MissionConfig, SessionConfig, save_config
    cfg = dataclasses.replace(MissionConfig(out=tmp_path), session=SessionConfig(
        mode="peer", connect=(f"tcp/127.0.0.1:{free_loopback_port()}",),
        listen=(f"tcp/127.0.0.1:{free_loopback_port()}",), wait_for_peers=1))
    save_config(cfg, tmp_path / "config.json")
    launcher = Launcher(tmp_path / "launcher.log")
    try:
        bad = launcher.spawn(["gate", "--no-such-flag"], tmp_path / "bad.log", append=False)
        assert bad.wait(60) == 2
        assert "Unrecognized options: --no-such-flag" in (tmp_path / "bad.log").read_text()
        # A module with nobody to connect to waits for its peer: it runs until killed.
        waiting = launcher.spawn(["gate", "--config", str(tmp_path / "config.json")],
                                 tmp_path / "gate.log", append=False)
        with pytest.raises(subprocess.TimeoutExpired):
            waiting.wait(0.5)
        assert waiting.poll() is None
        cmdline = Path(f"/proc/{waiting.pid}/cmdline").read_bytes()
        assert cmdline.startswith(b"rovergate gate --config"), cmdline
        waiting.kill()
        assert waiting.wait(30) == -signal.SIGKILL
        waiting.kill()  # an exited module is not signalled again (its pid may be reused)
    finally:
        launcher.close()
    assert launcher.proc.returncode == 0
