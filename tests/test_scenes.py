"""The scene suite: deterministic, documented, with free and traversable starts; mesh files."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest
import trimesh

from rover_sim.catalog import SCENES, SUITE, load_scene
from rover_sim.flyer import FlyerBody
from rover_sim.rover import RoverBody
from rovergate.config import FlyerConfig, RoverConfig, SceneConfig
from rovergate.errors import ConfigError

DOCS = Path(__file__).resolve().parents[1] / "docs" / "scenes.md"


def documented_d_scene() -> dict[str, float]:
    rows = re.findall(r"^\| `(\w+)` \| \w+ \| [^|]+ \| ([\d.]+) \|", DOCS.read_text(), re.M)
    return {name: float(d) for name, d in rows}


def test_suite_has_five_procedural_scenes_besides_arch_field():
    assert len(SUITE) >= 6 and "arch_field" in SUITE


@pytest.mark.parametrize("name", SUITE)
def test_procedural_scene_is_deterministic(name):
    a, b = SCENES[name].build(), SCENES[name].build()
    assert np.array_equal(a.terrain_z, b.terrain_z)
    assert len(a.objects) == len(b.objects) > 0
    assert all(np.array_equal(x.vertices, y.vertices)
               for x, y in zip(a.objects, b.objects, strict=True))
    assert a.bounds_m == b.bounds_m
    np.testing.assert_array_equal(a.surface_samples(3000), b.surface_samples(3000))


@pytest.mark.parametrize("name", list(SCENES))
def test_d_scene_is_what_the_docs_say(name):
    scene = load_scene(name)
    lo, hi = np.array(scene.bounds_m[:3]), np.array(scene.bounds_m[3:])
    assert scene.d_scene_m == pytest.approx(np.linalg.norm(hi - lo))
    assert documented_d_scene()[name] == pytest.approx(scene.d_scene_m, abs=0.006)


@pytest.mark.parametrize("name", list(SCENES))
def test_every_start_is_free_and_traversable_for_both_platforms(name):
    scene = load_scene(name)
    assert sorted(scene.starts) == ["a", "b", "c", "d", "e"]
    rover, flyer = RoverBody(scene, RoverConfig()), FlyerBody(scene, FlyerConfig(), 0.05)
    b = scene.bounds_m
    for start, (x, y, yaw) in scene.starts.items():
        assert b[0] < x < b[3] and b[1] < y < b[4], start
        assert rover.traversable(x, y, yaw), start
        assert rover.clearance(rover.base_pose(x, y, yaw)) >= 0.3, start
        assert flyer.clearance(flyer.start_state(x, y, yaw)[:3]) >= 0.2, start


def test_scenes_sample_about_100k_points_by_area():
    scene = load_scene("outpost")
    pts = scene.surface_samples(100_000, seed=0)
    assert 80_000 < len(pts) <= 100_000
    b = scene.bounds_m
    assert np.all((pts[:, 0] >= b[0]) & (pts[:, 0] <= b[3]))
    # By area: the flat ground (900 m^2 of about 1000+) holds most of the samples.
    ground = np.abs(pts[:, 2] - scene.height_at(pts[:, 0], pts[:, 1])) < 0.02
    assert 0.6 < ground.mean() < 0.95


def _write_test_mesh(path: Path) -> None:
    """A 20 m x 20 m ground with a 2 m block on it, in centimetres and Y-up (as many tools
    export)."""
    ground = trimesh.creation.box(extents=[2000, 2000, 10])
    ground.apply_translation([0, 0, -5])
    block = trimesh.creation.box(extents=[200, 200, 200])
    block.apply_translation([400, 300, 100])
    mesh = trimesh.util.concatenate([ground, block])
    mesh.apply_transform(trimesh.geometry.align_vectors([0, 0, 1], [0, 1, 0]))  # z-up -> y-up
    mesh.export(path)


@pytest.mark.parametrize("suffix", [".ply", ".obj"])
def test_a_mesh_file_is_a_scene(tmp_path, suffix):
    path = tmp_path / f"site{suffix}"
    _write_test_mesh(path)
    scene = load_scene(SceneConfig(name=str(path), up_axis="y", scale=0.01))
    b = scene.bounds_m
    assert b[3] - b[0] == pytest.approx(20.0, abs=0.01)
    assert b[4] - b[1] == pytest.approx(20.0, abs=0.01)
    assert b[5] == pytest.approx(2.0, abs=0.01)  # the block's top
    assert float(scene.height_at(0.0, 0.0)) == pytest.approx(0.0, abs=0.01)
    # The block is an obstacle, the ground is not.
    body = RoverBody(scene, RoverConfig())
    assert body.clearance(body.base_pose(2.8, 3.0, 0.0)) < 0  # across the block's face
    assert body.clearance(body.base_pose(-5.0, -5.0, 0.0)) > 0.3
    assert len(scene.starts) == 5
    for x, y, yaw in scene.starts.values():
        assert body.clearance(body.base_pose(x, y, yaw)) >= 0.3
    assert len(scene.surface_samples(20_000)) > 15_000


def test_a_bad_mesh_file_gets_one_line_saying_why(tmp_path):
    bad = tmp_path / "broken.ply"
    bad.write_text("this is not a mesh\n")
    with pytest.raises(ConfigError, match=r"broken\.ply"):
        load_scene(SceneConfig(name=str(bad)))
    with pytest.raises(ConfigError, match="does not exist"):
        load_scene(SceneConfig(name=str(tmp_path / "missing.obj")))
    with pytest.raises(ConfigError, match="up-axis"):
        load_scene(SceneConfig(name=str(bad), up_axis="w"))
    with pytest.raises(ConfigError, match="unknown scene"):
        load_scene("atlantis")


def test_rovergate_scenes_lists_and_draws(tmp_path, capsys):
    from mission.cli import COMMANDS
    assert COMMANDS["scenes"].main(["crater", "--render", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert "crater" in out and "d_scene" in out and "a=(" in out
    assert (tmp_path / "crater.png").stat().st_size > 10_000
