"""The real process set over Zenoh on loopback: coverage grows, processes exit cleanly, the
numbers equal the in-process loop's to the last digit, and faults are reported, not hidden."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import threading
from pathlib import Path

import numpy as np
import pytest
import zenoh
from conftest import StatusWatcher, run_cli
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from rovergate.session import free_loopback_port

ROOT = Path(__file__).resolve().parents[1]

pytestmark = pytest.mark.e2e

def test_process_set_runs_and_matches_in_process(tmp_path: Path):
    procs = run_cli("run", "--steps", "10", "--out", str(tmp_path / "p"))
    assert procs.returncode == 0, procs.stderr[-3000:]
    inproc = run_cli("run", "--steps", "10", "--in-process", "--out", str(tmp_path / "i"))
    assert inproc.returncode == 0, inproc.stderr[-3000:]
    p = json.loads((tmp_path / "p" / "metrics.json").read_text())
    i = json.loads((tmp_path / "i" / "metrics.json").read_text())
    assert p["mode"] == "processes" and i["mode"] == "in-process"
    cov = p["coverage"]
    assert len(cov) == 11 and cov[-1] > cov[0] > 0
    assert all(b >= a for a, b in zip(cov, cov[1:], strict=False))
    # The same seed gives the same per-step coverage in both modes, to the last digit.
    assert (tmp_path / "p" / "coverage.csv").read_text() == \
        (tmp_path / "i" / "coverage.csv").read_text()
    assert p["path_length_m"] == i["path_length_m"] and p["collisions"] == i["collisions"]
    assert p["dropped_messages"] == 0
    assert set(p["median_stage_s"]) >= {"render", "integrate", "gate", "plan", "execute"}
    for name in ("coverage.png", "map_topdown.png", "config.json", "coverage.csv"):
        assert (tmp_path / "p" / name).stat().st_size > 0
    for module in ("sim", "mapper", "gate", "planner"):
        log = (tmp_path / "p" / "logs" / f"{module}.log").read_text()
        assert "liveliness token" in log and "mission done" in log, module
    # What a new user reads: no pybullet banner, no configuration dump, counts in their number,
    # the bag announced, and the end naming the files to open.
    said = procs.stderr + procs.stdout
    assert "pybullet build time" not in said and '"session": {' not in said
    assert "1 window in 10 steps" in said and "light time 2 steps" in said, said[-3000:]
    assert "recording every topic into" in said and "0 collisions" in said
    report = next(line for line in said.splitlines() if "report in" in line)
    assert "metrics.json, coverage.csv, coverage.png, map_topdown.png" in report, report
    assert "rovergate replay" in report, report


def test_independent_subscriber_decodes_the_planner_occupancy(tmp_path: Path, launch):
    """A session that knows only zenoh and rosbags reads the planner-facing map."""
    port = free_loopback_port()
    mission = launch("run", "--steps", "8", "--out", str(tmp_path), "--listen",
                     f"tcp/127.0.0.1:{port}")
    store = get_typestore(Stores.ROS2_HUMBLE)
    store.register(get_types_from_msg((ROOT / "rovergate/msg/CloudUpdate.msg").read_text(),
                                      "rovergate_msgs/msg/CloudUpdate"))
    got: list = []
    done = threading.Event()

    def on_sample(sample):
        schema = str(sample.encoding)
        msg = store.deserialize_cdr(sample.payload.to_bytes(), "rovergate_msgs/msg/CloudUpdate")
        got.append((schema, msg))
        if msg.base_step == -1:  # a keyframe: the whole map
            done.set()

    # The mission's session listens before it starts any module.
    mission.wait_for_line(r"started sim \(pid")
    conf = zenoh.Config()
    conf.insert_json5("mode", '"client"')
    conf.insert_json5("connect/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    session = zenoh.open(conf)
    sub = session.declare_subscriber("rover/map/occupancy/planner", on_sample)
    try:
        assert done.wait(120), "no planner-facing occupancy received within 120 s"
    finally:
        sub.undeclare()
        session.close()
    assert mission.finish() == 0, mission.text[-3000:]
    schema, update = next((s, m) for s, m in got if m.base_step == -1)
    assert schema == "application/cdr;rovergate_msgs/msg/CloudUpdate"
    msg = update.points  # a sensor_msgs/PointCloud2: the whole map of its step
    assert [f.name for f in msg.fields] == ["x", "y", "z", "source", "views", "channels"]
    assert msg.width > 1000 and msg.width == update.size and msg.header.frame_id == "map"
    xyz = np.frombuffer(msg.data.tobytes(), dtype=np.dtype(
        {"names": ["x", "y", "z"], "formats": ["<f4"] * 3, "offsets": [0, 4, 8],
         "itemsize": msg.point_step}))
    assert np.isfinite(xyz["x"]).all() and np.abs(xyz["x"]).max() < 30


def test_a_module_that_dies_stops_the_mission_with_its_name(tmp_path: Path, launch):
    """With no restarts allowed (tests/test_health.py covers restarting), a module's death
    ends the mission with its name, and no process is left behind."""
    port = free_loopback_port()
    mission = launch("run", "--steps", "500", "--out", str(tmp_path), "--max-restarts", "0",
                     "--listen", f"tcp/127.0.0.1:{port}")
    mission.wait_for_line("all modules ready")
    watcher = StatusWatcher(port)
    try:
        watcher.wait_step(2)  # the loop is running
        os.kill(mission.pid("planner"), signal.SIGKILL)
        assert mission.finish(120) == 1
    finally:
        watcher.close()
    assert "module 'planner' exited with code -9 during the mission, after 0 restarts" in \
        mission.text
    # The mission waits for every module to exit before it does.
    config = str(tmp_path / "config.json")
    left = subprocess.run(["pgrep", "-f", f"--config {config}"], capture_output=True, text=True)
    assert left.stdout.strip() == "", "modules left running"


def test_learned_condition_feeds_the_prediction_to_the_planner(tmp_path: Path):
    """The process set and the in-process loop, in the learned condition: the mapper's
    prediction is non-empty, it enters the planner-facing map, and both modes agree."""
    procs = run_cli("run", "--condition", "learned", "--steps", "3", "--out",
                    str(tmp_path / "p"))
    assert procs.returncode == 0, procs.stderr[-3000:]
    inproc = run_cli("run", "--condition", "learned", "--steps", "3", "--in-process", "--out",
                     str(tmp_path / "i"))
    assert inproc.returncode == 0, inproc.stderr[-3000:]
    p = json.loads((tmp_path / "p" / "metrics.json").read_text())
    i = json.loads((tmp_path / "i" / "metrics.json").read_text())
    assert len(p["predicted_points_per_step"]) == 3
    assert min(p["predicted_points_per_step"]) > 100
    # Equation 2, learned: the planner receives every predicted point beside S_t.
    assert p["planner_predicted_per_step"] == p["predicted_points_per_step"]
    for key in ("predicted_points_per_step", "planner_predicted_per_step", "path_length_m"):
        assert p[key] == i[key], key
    assert (tmp_path / "p" / "coverage.csv").read_text() == \
        (tmp_path / "i" / "coverage.csv").read_text()


def test_gated_condition_withholds_part_of_the_prediction(tmp_path: Path):
    r = run_cli("run", "--condition", "gated", "--steps", "4", "--in-process", "--out",
                str(tmp_path))
    assert r.returncode == 0, r.stderr[-3000:]
    m = json.loads((tmp_path / "metrics.json").read_text())
    pred, kept, held = (m[k] for k in ("predicted_points_per_step",
                                       "planner_predicted_per_step", "suppressed_per_step"))
    assert all(k + h == n for n, k, h in zip(pred, kept, held, strict=True))
    assert held[0] == 0  # one frustum is fewer than K = 2
    assert sum(held) > 0
    # The evaluator's audit: of the withheld points, how many were true false positives.
    fp = m["suppressed_fp_per_step"]
    assert len(fp) == len(held) and all(0 <= f <= h for f, h in zip(fp, held, strict=True))
    assert m["suppressed_fp_share"] == sum(fp) / sum(held)


def test_ground_truth_reaches_only_the_evaluator(tmp_path: Path, launch):
    """Under obs, learned and gated, nothing from <ns>/truth/... reaches any module but the
    mission's evaluator; under an oracle condition the gate gets the reference too.

    Truth travels only as answers of the simulator's queryables, and the simulator logs every
    answer with the requester's name; a spy session subscribed to <ns>/truth/** sees that
    nothing is ever published there either."""
    served = {}
    for condition in ("obs", "learned", "gated", "learned-fp"):
        port = free_loopback_port()
        out = tmp_path / condition
        spied: list[str] = []
        mission = launch("run", "--condition", condition, "--steps", "2", "--out", str(out),
                         "--listen", f"tcp/127.0.0.1:{port}")
        mission.wait_for_line(r"started sim \(pid")  # the mission's session listens
        conf = zenoh.Config()
        conf.insert_json5("mode", '"client"')
        conf.insert_json5("connect/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
        session = zenoh.open(conf)
        sub = session.declare_subscriber("rover/truth/**", spied.append)
        code = mission.finish()
        sub.undeclare()
        session.close()
        assert code == 0, mission.text[-3000:]
        assert [str(s.key_expr) for s in spied] == [], condition
        log = (out / "logs" / "sim.log").read_text()
        served[condition] = sorted(line.split("served ")[1] for line in log.splitlines()
                                   if "served " in line)
    evaluator_only = ["rover/truth/surface_samples to mission"]
    assert served["obs"] == served["learned"] == served["gated"] == evaluator_only
    assert served["learned-fp"] == sorted(evaluator_only + ["rover/truth/occupancy to gate"])


def test_truth_condition_runs_and_is_reproducible(tmp_path: Path):
    a = run_cli("run", "--condition", "truth", "--steps", "3", "--in-process", "--out",
                str(tmp_path / "a"))
    b = run_cli("run", "--condition", "truth", "--steps", "3", "--in-process", "--out",
                str(tmp_path / "b"))
    assert a.returncode == 0 == b.returncode, a.stderr[-2000:]
    assert (tmp_path / "a" / "coverage.csv").read_text() == \
        (tmp_path / "b" / "coverage.csv").read_text()


def test_bad_flags_and_files_get_one_line(tmp_path: Path):
    r = run_cli("run", "--scene.name", "atlantis", "--out", str(tmp_path))
    assert r.returncode != 0 and "unknown scene 'atlantis'; choose one of: arch_field" in r.stderr
    r = run_cli("run", "--start", "z", "--steps", "1", "--in-process", "--out", str(tmp_path))
    assert r.returncode != 0 and "has no start 'z'" in r.stderr
    bad = tmp_path / "bad.json"
    bad.write_text('{"stepz": 3}')
    r = run_cli("run", "--config", str(bad))
    assert r.returncode != 0 and "unknown key 'stepz'" in r.stderr


def test_degraded_flyer_mission_is_the_same_in_processes_and_recorded(tmp_path: Path):
    """A flyer with every degradation on, in a new scene: the process set and the in-process
    loop agree to the last digit, and the settings are in the run's config."""
    flags = ["--steps", "5", "--scene", "outpost", "--platform", "flyer", "--start", "c",
             "--sensing.noise-frac", "0.01", "--sensing.dropout-blob-frac", "0.05",
             "--sensing.dropout-pixel-prob", "0.01", "--sensing.grazing-max-deg", "80",
             "--sensing.drift-xy-m", "0.03", "--sensing.drift-yaw-deg", "0.5"]
    procs = run_cli("run", *flags, "--out", str(tmp_path / "p"))
    assert procs.returncode == 0, procs.stderr[-3000:]
    inproc = run_cli("run", *flags, "--in-process", "--out", str(tmp_path / "i"))
    assert inproc.returncode == 0, inproc.stderr[-3000:]
    assert (tmp_path / "p" / "coverage.csv").read_text() == \
        (tmp_path / "i" / "coverage.csv").read_text()
    cfg = json.loads((tmp_path / "p" / "config.json").read_text())
    assert cfg["platform"] == "flyer" and cfg["scene"]["name"] == "outpost"
    assert cfg["sensing"]["noise_frac"] == 0.01 and cfg["sensing"]["drift_xy_m"] == 0.03
    m = json.loads((tmp_path / "p" / "metrics.json").read_text())
    assert m["final_pose_error_m"] > 0 and m["coverage"][-1] > m["coverage"][0]


def test_unknown_platform_gets_one_line():
    r = run_cli("run", "--platform", "boat", "--steps", "1", "--in-process")
    assert r.returncode != 0 and "unknown platform 'boat'" in r.stderr
    assert "Traceback" not in r.stderr
