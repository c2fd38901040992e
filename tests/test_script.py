"""Mission scripts (issue 17, part 4): a TOML mission file with an operations timeline that a
ground station plays through the mission's authenticated uplink, and the Python API
(``from mission import Mission``) that the examples use."""

from __future__ import annotations

import json
import subprocess
import sys
import urllib.request
from pathlib import Path

import pytest

from mission.script import Mission, load_script
from rovergate.errors import ConfigError
from tests.conftest import read_metrics, run_cli

ROOT = Path(__file__).resolve().parents[1]
EXAMPLE = ROOT / "examples" / "mission.toml"


def test_the_example_mission_file_reads_as_its_settings_and_timeline():
    script = load_script(EXAMPLE)
    assert script.config.platform == "rover" and script.config.scene.name == "arch_field"
    assert script.config.contact.period_steps == 6
    assert [(e.step, e.window, e.command) for e in script.timeline] == [
        (1, None, "set planner.n_candidates=24"), (None, 2, "condition gated")]


@pytest.mark.parametrize("text, names", [
    ("stepz = 3", "unknown key 'stepz'"),
    ("steps = 'ten'", "`steps` must be an integer"),
    ("[planner]\nname = 3", "`planner.name` must be a string"),
    ("planner = 'beam'", "`planner` is a section"),
    ("condition = 3", "`condition` must be a string"),
    ("record_compression = 'lz4'", "`record_compression` must be one of 'none', 'zstd'"),
    ("[[timeline]]\nstep = 2\ncommand = 'fly away'", "unknown command 'fly away'"),
    ("[[timeline]]\nstep = 2\nwindow = 1\ncommand = 'pause'", "exactly one of `step`"),
    ("[[timeline]]\nwindow = 0\ncommand = 'pause'", "`window` must be an integer of at least 1"),
    ("[[timeline]]\nstep = 2", "needs `command`"),
    # What the rover would refuse in flight is refused before anything starts.
    ("[[timeline]]\nstep = 2\ncommand = 'set planner.n_candidates=9999'",
     "planner.n_candidates must be between 1 and 256, got '9999'"),
    ("[[timeline]]\nstep = 2\ncommand = 'set gate.k=2.5'", "gate.k takes an integer"),
    ("[[timeline]]\nstep = 2\ncommand = 'set scene.name=3'", "cannot set 'scene.name'"),
    ("[[timeline]]\nstep = 2\ncommand = 'condition telepathy'", "unknown condition"),
    ("[[timeline]]\nstep = 2\ncommand = 'planner nowhere'", "unknown planner 'nowhere'"),
    ("[ground]\nkey = 'x'", "[ground] takes only `credentials`"),
    ("[ground]\nweb = 'yes'", "[ground] `web` must be true or false"),
    ("[ground]\nweb = true\nweb_port = 70000", "`web_port` must be a port"),
])
def test_a_bad_mission_file_is_refused_in_one_line_naming_what(tmp_path: Path, text, names):
    path = tmp_path / "bad.toml"
    path.write_text(text + "\n")
    with pytest.raises(ConfigError) as err:
        load_script(path)
    assert names in str(err.value) and "\n" not in str(err.value)
    assert str(path) in str(err.value) or "unknown key" in str(err.value)


def test_not_toml_is_refused_with_the_parsers_reason(tmp_path: Path):
    path = tmp_path / "bad.toml"
    path.write_text("steps = \n")
    with pytest.raises(ConfigError, match="is not valid TOML"):
        load_script(path)


def test_the_api_configures_like_the_file():
    import mission
    assert mission.Mission is Mission  # `from mission import Mission`
    mission = Mission(steps=20, scene={"name": "crater"}, contact={"period_steps": 10})
    assert (mission.config.steps, mission.config.scene.name) == (20, "crater")
    assert mission.config.contact.period_steps == 10
    assert mission.config.contact.window_steps == 5  # the rest of the section is kept
    mission.at_step(3, "pause").at_window(1, "resume")
    assert [(e.step, e.window) for e in mission.timeline] == [(3, None), (None, 1)]
    with pytest.raises(ConfigError, match="unknown command"):
        mission.at_step(1, "rm -rf /")
    with pytest.raises(ConfigError, match="unknown key"):
        Mission(planner={"nme": "beam"})


def test_a_timeline_outside_the_mission_is_refused_before_anything_starts(tmp_path: Path):
    r = run_cli("run", str(EXAMPLE), "--steps", "4", "--out", str(tmp_path / "run"))
    assert r.returncode == 2 and "has 1 windows in 4 steps" in r.stderr, r.stderr[-2000:]
    assert not (tmp_path / "run").exists()  # no credentials made, nothing written
    r = run_cli("run", str(EXAMPLE), "--steps", "40", "--resume", "--out", str(tmp_path / "r"))
    assert r.returncode == 2 and "a timeline is not resumed" in r.stderr, r.stderr[-2000:]
    # A flag after the file that makes a timeline command one the rover would refuse.
    bad = tmp_path / "bad.toml"
    bad.write_text(EXAMPLE.read_text().replace("set planner.n_candidates=24",
                                               "set planner.n_candidates=9999"))
    r = run_cli("run", str(bad), "--out", str(tmp_path / "b"))
    assert r.returncode == 2 and r.stderr.count("\n") == 1 and \
        "planner.n_candidates must be between 1 and 256" in r.stderr, r.stderr[-2000:]
    assert not (tmp_path / "b").exists()


@pytest.mark.e2e
def test_the_example_mission_file_runs_and_its_commands_are_acknowledged(tmp_path: Path):
    out = tmp_path / "run"
    r = run_cli("run", str(EXAMPLE), "--steps", "12", "--out", str(out))
    assert r.returncode == 0, r.stderr[-3000:]
    metrics = read_metrics(out)
    assert metrics["steps"] == 12
    # Both commands went up the mutual-TLS uplink (fresh credentials), ran and came back
    # acknowledged on the downlink.
    assert (out / "credentials" / "station" / "station.pem").is_file()
    assert "the ground link is mutual TLS" in r.stderr
    rows = [json.loads(line) for line in
            (out / "ground" / "received.jsonl").read_text().splitlines()]
    acks = {row["verb"]: row for row in rows if row["kind"] == "command_ack"}
    assert set(acks) == {"set", "condition"}
    executed = {c["verb"]: c["step"] for c in metrics["link"]["commands"]}
    assert executed == {v: a["executed_step"] for v, a in acks.items()}
    assert json.loads((out / "ground" / "unsent.json").read_text()) == []
    # The first command has windows to spare. The second is sent when the ground sees the
    # second window open, in wall time; on a machine so loaded that it reached the rover only
    # after the last step, it is acknowledged as rejected, saying so, and changed nothing.
    assert acks["set"]["state"] == "executed", acks
    if acks["condition"]["state"] == "executed":
        # It took effect: the gate's configuration after it says so.
        assert json.loads((out / "config.2.json").read_text())["condition"] == "gated"
    else:
        assert "the mission had ended" in acks["condition"]["detail"], acks


@pytest.mark.e2e
def test_a_mission_files_ground_station_serves_the_console(tmp_path: Path):
    """`web = true` in [ground], with no timeline: the run's own ground station serves the
    console on loopback, names it in the log, and the console reports the mission's end."""
    from tests.conftest import RovergateProcess
    path = tmp_path / "web.toml"
    path.write_text('steps = 30\ncondition = "obs"\n[contact]\nperiod_steps = 4\n'
                    'window_steps = 2\n[ground]\nweb = true\n')
    m = RovergateProcess(["run", str(path), "--out", str(tmp_path / "m"), "--no-progress"])
    try:
        url = m.wait_for_line(r"console on (http://127\.0\.0\.1:\d+/)").group(1)
        with urllib.request.urlopen(url + "api/state", timeout=10) as response:
            state = json.loads(response.read())
        assert response.status == 200 and "rover" in state and "commands" in state
        assert m.finish(300) == 0, m.text[-3000:]
    finally:
        m.kill()
    assert load_script(path).web
    rows = [json.loads(line) for line in
            (tmp_path / "m" / "ground" / "received.jsonl").read_text().splitlines()]
    assert [r["event"] for r in rows if r["kind"] == "event"][:3] == [
        "mission-started", "contact-plan", "command-dictionary"]


@pytest.mark.e2e
def test_the_python_api_example_runs_a_mission_and_reads_its_record(tmp_path: Path):
    r = subprocess.run([sys.executable, str(ROOT / "examples" / "run_mission.py"), "--steps",
                        "12", "--out", str(tmp_path / "api")], capture_output=True, text=True,
                       timeout=300, cwd=ROOT)
    assert r.returncode == 0, r.stderr[-3000:]
    acks = [line for line in r.stdout.splitlines() if line.startswith("command ")]
    assert "final coverage" in r.stdout and len(acks) == 3, r.stdout
    # Each ran, or (a window command on a loaded machine) came after the end and says so.
    assert all(" executed at step " in a or "the mission had ended" in a for a in acks), acks
