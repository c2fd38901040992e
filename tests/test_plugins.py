"""Planners and scenes from a package of the user's own, registered through the
``rovergate.planners`` and ``rovergate.scenes`` entry-point groups (``planner/planner.py``,
``PLANNER_GROUP``; ``rover_sim/catalog.py``, ``SCENE_GROUP``): the test builds and installs
such a package into a directory of its own, and a mission runs its planner on its scene."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
from conftest import ROVERGATE

pytestmark = pytest.mark.e2e

PLUGIN = '''
import os

from planner.planner import GreedyPlanner


class Logged(GreedyPlanner):
    """The greedy planner, writing every step it plans to $RG_TEST_PLANNER_LOG."""

    def plan(self, step, occupancy, T_map_base, *args, **kwargs):
        with open(os.environ["RG_TEST_PLANNER_LOG"], "a") as f:
            f.write(f"{step}\\n")
        return super().plan(step, occupancy, T_map_base, *args, **kwargs)


class NotAPlanner:
    pass


def small_crater():
    """The suite's crater, under the package's own name."""
    from rover_sim import suite
    scene = suite.build_crater()
    scene.name = "small_crater"
    return scene


def not_a_scene():
    return "crater"


class Eager:
    """The frustum gate at K = 1: a prediction is withheld after one frame without support."""

    from gate.filter import ObservationGate
    from gate.gate import Variant, without_unsupported
    from rovergate.conditions import Condition
    condition = Condition("gated-eager", "the frustum gate at K = 1", needs_prediction=True,
                          needs_truth=False, withholds=True)
    variant = Variant(lambda cfg, eps, near, far: Eager.ObservationGate(1, eps, near, far),
                      without_unsupported)


class Misnamed:
    from rovergate.conditions import Condition
    condition = Condition("other", "a condition under another name", True, False)
    variant = None
'''

PYPROJECT = '''
[build-system]
requires = ["setuptools"]
build-backend = "setuptools.build_meta"

[project]
name = "rg-test-planner"
version = "0.1"

[project.entry-points."rovergate.planners"]
logged = "rg_test_planner:Logged"
notaplanner = "rg_test_planner:NotAPlanner"
beam = "rg_test_planner:Logged"

[project.entry-points."rovergate.scenes"]
small_crater = "rg_test_planner:small_crater"
notascene = "rg_test_planner:not_a_scene"
crater = "rg_test_planner:small_crater"

[project.entry-points."rovergate.conditions"]
gated-eager = "rg_test_planner:Eager"
misnamed = "rg_test_planner:Misnamed"

[tool.setuptools]
py-modules = ["rg_test_planner"]
'''


@pytest.fixture(scope="module")
def installed(tmp_path_factory) -> dict[str, str]:
    """The environment of a process that has the package installed (into a directory of its
    own, put on PYTHONPATH: the shared .venv is left as it was)."""
    root = tmp_path_factory.mktemp("plugin")
    (root / "src").mkdir()
    (root / "src" / "rg_test_planner.py").write_text(PLUGIN)
    (root / "src" / "pyproject.toml").write_text(PYPROJECT)
    r = subprocess.run([sys.executable, "-m", "pip", "install", "-q", "--no-deps",
                        "--no-build-isolation", "--no-index", "--target", str(root / "site"),
                        str(root / "src")], capture_output=True, text=True, timeout=180)
    assert r.returncode == 0, r.stderr[-2000:]
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(root / "site"),
                                                      env.get("PYTHONPATH")]))
    env["RG_TEST_PLANNER_LOG"] = str(root / "planned.txt")
    return env


def test_a_planner_registered_by_another_package_runs_in_a_mission(installed, tmp_path):
    r = subprocess.run([*ROVERGATE, "run", "--planner.name", "logged", "--steps", "4",
                        "--no-progress", "--no-record", "--out", str(tmp_path / "m")],
                       capture_output=True, text=True, timeout=240, env=installed)
    assert r.returncode == 0, r.stderr[-3000:]
    # The planner module's process planned every step with the package's class.
    assert Path(installed["RG_TEST_PLANNER_LOG"]).read_text().split() == ["0", "1", "2", "3"]
    metrics = json.loads((tmp_path / "m" / "metrics.json").read_text())
    assert len(metrics["coverage"]) == 5 and metrics["path_length_m"] > 0
    # A built-in name is not the package's to take: the warning says so, beam stays beam.
    assert "'beam' of rg_test_planner:Logged is a built-in name" in r.stderr


def test_a_registered_planner_that_is_not_one_is_one_line(installed, tmp_path):
    r = subprocess.run([*ROVERGATE, "run", "--planner.name", "notaplanner", "--steps", "2",
                        "--in-process", "--no-progress", "--no-record",
                        "--out", str(tmp_path / "m")],
                       capture_output=True, text=True, timeout=120, env=installed)
    assert r.returncode == 2, r.stderr[-2000:]
    last = r.stderr.strip().splitlines()[-1]
    assert "is not a subclass of planner.planner.Planner" in last, r.stderr[-2000:]
    r = subprocess.run([*ROVERGATE, "run", "--planner.name", "nosuch", "--steps", "2",
                        "--in-process", "--no-progress", "--no-record",
                        "--out", str(tmp_path / "n")],
                       capture_output=True, text=True, timeout=120, env=installed)
    assert r.returncode == 2 and "choose one of: auto, beam, greedy, logged" in r.stderr


def test_a_scene_registered_by_another_package_is_listed_and_runs_in_a_mission(installed,
                                                                              tmp_path):
    r = subprocess.run([*ROVERGATE, "scenes", "small_crater"], capture_output=True, text=True,
                       timeout=240, env=installed)
    assert r.returncode == 0, r.stderr[-2000:]
    assert r.stdout.startswith("small_crater") and "plugin" in r.stdout.splitlines()[0]
    # A suite name is not the package's to take: the warning says so, crater stays crater.
    assert "'crater' of rg_test_planner:small_crater is a suite scene's name" in r.stderr
    r = subprocess.run([*ROVERGATE, "run", "--scene.name", "small_crater", "--planner.name",
                        "logged", "--steps", "3", "--in-process", "--no-progress",
                        "--no-record", "--out", str(tmp_path / "m")],
                       capture_output=True, text=True, timeout=240, env=installed)
    assert r.returncode == 0, r.stderr[-3000:]
    config = json.loads((tmp_path / "m" / "config.json").read_text())
    assert config["scene"]["name"] == "small_crater" and config["scene"]["d_scene_m"] > 0
    assert len(json.loads((tmp_path / "m" / "metrics.json").read_text())["coverage"]) == 4
    r = subprocess.run([*ROVERGATE, "run", "--scene.name", "notascene", "--steps", "2",
                        "--in-process", "--no-progress", "--no-record",
                        "--out", str(tmp_path / "n")],
                       capture_output=True, text=True, timeout=120, env=installed)
    assert r.returncode == 2, r.stderr[-2000:]
    assert r.stderr.strip().splitlines()[-1].endswith(
        "built a str, not a rover_sim.scene.Scene; return one"), r.stderr[-2000:]


def test_a_condition_registered_by_another_package_runs_in_a_mission_and_gates(installed,
                                                                               tmp_path):
    r = subprocess.run([*ROVERGATE, "run", "--condition", "gated-eager", "--steps", "6",
                        "--no-progress", "--no-record", "--out", str(tmp_path / "m")],
                       capture_output=True, text=True, timeout=240, env=installed)
    assert r.returncode == 0, r.stderr[-3000:]
    metrics = json.loads((tmp_path / "m" / "metrics.json").read_text())
    assert metrics["conditions"] == [[0, "gated-eager"]]
    # Its gate ran in the gate's process: it withheld part of the prediction (K = 1).
    assert sum(metrics["suppressed_per_step"]) > 0, metrics["suppressed_per_step"]
    r = subprocess.run([*ROVERGATE, "run", "--condition", "misnamed", "--steps", "2",
                        "--in-process", "--no-progress", "--no-record",
                        "--out", str(tmp_path / "n")],
                       capture_output=True, text=True, timeout=120, env=installed)
    assert r.returncode == 2, r.stderr[-2000:]
    assert "condition 'misnamed' (rg_test_planner:Misnamed) needs a `condition`" in \
        r.stderr.strip().splitlines()[-1], r.stderr[-2000:]
