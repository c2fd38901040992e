"""The shape of the system: one graph declaration that everything derives from, logic that
loads without a transport, settings refused before anything starts."""

from __future__ import annotations

import dataclasses
import subprocess
import sys
from pathlib import Path

import pytest

from mission.run import check_runnable
from mission.runtime.journal import KEEP_ALL, KEEP_LAST
from mission.runtime.transport import InProcessTransport
from rovergate import graph
from rovergate.config import GateConfig, MissionConfig, PlannerConfig, SensorConfig
from rovergate.errors import CheckpointError, ConfigError, UnknownNameError

ROOT = Path(__file__).resolve().parents[1]


def test_the_graph_is_consistent_and_everything_derives_from_it():
    graph.check_graph()
    assert graph.LAUNCHED == ("sim", "mapper", "gate", "planner")
    assert graph.stage_module() == {"execute": "sim", "render": "sim", "integrate": "mapper",
                                    "gate": "gate", "traverse": "planner", "plan": "planner"}
    # The journal keeps every step of what modules replay, the last steps of the rest.
    assert {"status", "path", "depth", "camera_info", "pose", "pose_cov", "base_pose",
            "execution", "hazcam_front", "hazcam_rear"} == KEEP_ALL
    assert {"surface", "predicted", "planner_map"} == KEEP_LAST
    assert {m.name: m.progress for m in graph.MODULES.values() if m.launched} == {
        "sim": "base_pose", "mapper": "predicted", "gate": "planner_map", "planner": "path"}
    # What a ground command restarts is what is built from the setting it changes.
    assert graph.readers("condition") == ("mapper", "gate")
    assert graph.readers("hazcam") == ("sim", "mapper", "planner")
    assert graph.readers("gate") == ("gate",) and graph.readers("planner") == ("planner",)
    # Every topic a module reads has exactly one producer in the graph.
    for m in graph.MODULES.values():
        for i in m.inputs.values():
            assert graph.producer(i.topic) is not None


def test_every_launched_module_has_its_logic():
    from mission.runtime.modules import LOGIC, make_logic  # noqa: F401 (the table is the check)
    assert tuple(LOGIC) == graph.LAUNCHED
    import importlib
    for name, where in LOGIC.items():
        module, _, cls = where.partition(":")
        assert getattr(importlib.import_module(module), cls).spec is graph.MODULES[name]


def test_every_platform_has_its_body_and_its_motion_model():
    # A platform is one registration in rovergate.platforms plus its classes under its name;
    # the modules ask it what it has (cfg.vehicle) rather than compare names.
    from planner.platforms import MOTION_MODELS
    from rover_sim.sim import BODIES
    from rovergate.platforms import PLATFORMS
    assert set(BODIES) == set(MOTION_MODELS) == set(PLATFORMS)
    for name, p in PLATFORMS.items():
        cfg = MissionConfig(platform=name)
        assert cfg.vehicle is p and p.dims == (3 if p.flies else 2)
        from planner.planner import planner_name
        assert planner_name(cfg) == p.default_planner
    with pytest.raises(UnknownNameError, match="unknown platform 'boat'; choose one of: rover, "
                                               "flyer"):
        assert MissionConfig(platform="boat").vehicle


def test_a_broken_declaration_is_refused(monkeypatch):
    bad = dataclasses.replace(graph.MODULES["planner"],
                              inputs={"map": graph.Input("no_such_topic")})
    monkeypatch.setitem(graph.MODULES, "planner", bad)
    with pytest.raises(ValueError, match="unknown topic no_such_topic"):
        graph.check_graph()


def test_module_logic_loads_without_zenoh():
    code = ("import gate.gate, gate.logic, mapper.mapper, mapper.logic, planner.planner, "
            "planner.logic, rover_sim.sim, rover_sim.logic, mission.scoring.coverage, "
            "mission.scoring.metrics, mission.runtime.loop, mission.runtime.transport, "
            "mission.runtime.supervisor, rovergate.config, sys; "
            "assert 'zenoh' not in sys.modules, 'zenoh was imported'")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                       cwd=ROOT, timeout=120)
    assert r.returncode == 0, r.stderr[-2000:]


def _cfg(**kw) -> MissionConfig:
    return dataclasses.replace(MissionConfig(progress=False), **kw)


@pytest.mark.parametrize(("change", "error", "match"), [
    ({"start": "z"}, UnknownNameError, "has no start 'z'; choose one of: a, b, c, d, e"),
    ({"condition": "psychic"}, UnknownNameError, "unknown condition 'psychic'"),
    ({"platform": "boat"}, UnknownNameError, "unknown platform 'boat'"),
    ({"steps": 0}, ConfigError, "--steps must be at least 1"),
    ({"max_restarts": -1}, ConfigError, "--max-restarts must be at least 0"),
    ({"step_timeout_s": 0.0}, ConfigError, "--step-timeout-s must be positive"),
    ({"gate": GateConfig(epsilon_frac=0.0)}, ConfigError, "--gate.epsilon-frac must be positive"),
    ({"sensor": SensorConfig(min_range_m=5.0, max_range_m=2.0)}, ConfigError,
     "--sensor.max-range-m .* must exceed"),
    ({"planner": PlannerConfig(beam_discount=1.5)}, ConfigError,
     "--planner.beam-discount must be between 0 and 1, got 1.5"),
])
def test_bad_settings_are_refused_before_anything_starts(change, error, match):
    with pytest.raises(error, match=match):
        check_runnable(_cfg(**change))


def test_bad_planner_and_checkpoint_are_refused_before_anything_starts(tmp_path):
    cfg = _cfg()
    with pytest.raises(UnknownNameError, match="unknown planner 'astar'"):
        check_runnable(dataclasses.replace(cfg, planner=dataclasses.replace(
            cfg.planner, name="astar")))
    missing = dataclasses.replace(cfg.mapper, checkpoint=str(tmp_path / "none.pt"))
    with pytest.raises(CheckpointError, match="missing"):
        check_runnable(dataclasses.replace(cfg, condition="learned", mapper=missing))


def test_in_process_transport_routes_by_the_graph():
    """One tick runs the modules whose inputs are complete, in the graph's order: after the
    tick of step 0 the mission has S_0 and the base pose of step 0, and nothing of step 1."""
    from rover_sim.catalog import resolve_scene
    from rovergate.types import MissionStatus
    cfg = _cfg(steps=2)
    resolve_scene(cfg.scene)
    t = InProcessTransport(cfg)
    t.start()
    try:
        t.tick(MissionStatus(0, 2, "running", "obs", 0.0, 0))
        assert len(t.receive("surface", 0)) > 100
        assert t.receive("base", 0).position.shape == (3,)
        with pytest.raises(Exception, match="no path of step 0"):
            t.receive("path", 0) and t.receive("path", 0)  # the first takes it; none is left
        assert {x.module for x in t.timings()} == {"render", "integrate", "gate", "traverse",
                                               "plan"}
    finally:
        t.finish(MissionStatus(0, 2, "done", "obs", 0.0, 0), failed=False)


def test_a_config_saved_before_a_setting_was_retired_still_loads(tmp_path):
    import json

    from rovergate.config import load_config, save_config
    path = tmp_path / "config.json"
    save_config(MissionConfig(), path)
    data = json.loads(path.read_text())
    data["planner"]["known_ground_only"] = True  # retired by issue 26
    path.write_text(json.dumps(data))
    assert load_config(path).planner == MissionConfig().planner
    data["planner"]["no_such_setting"] = 1  # anything else is still refused, by name
    path.write_text(json.dumps(data))
    with pytest.raises(ConfigError, match="no_such_setting"):
        load_config(path)


def test_counts_read_in_their_number():
    from rovergate.logs import plural
    assert plural(1, "collision") == "1 collision" and plural(0, "window") == "0 windows"
    assert plural(2, "step") == "2 steps" and plural(3, "child", "children") == "3 children"
