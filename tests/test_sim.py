"""The world: deterministic scene, free starts, honest depth, collisions between waypoints."""

from __future__ import annotations

import numpy as np
import pytest

from mapper.integrate import backproject
from rover_sim.rover import RoverBody
from rover_sim.sim import RoverSim
from rover_sim.suite import build_arch_field
from rovergate.config import MissionConfig, RoverConfig
from rovergate.types import PlanPath, Pose


def test_scene_is_deterministic(scene):
    again = build_arch_field()
    assert np.array_equal(scene.terrain_z, again.terrain_z)
    assert all(np.array_equal(a.vertices, b.vertices)
               for a, b in zip(scene.objects, again.objects, strict=True))
    np.testing.assert_array_equal(scene.surface_samples(5000, seed=0),
                                  again.surface_samples(5000, seed=0))


def test_d_scene_is_the_diagonal_of_the_box_of_interest(scene):
    lo, hi = np.array(scene.bounds_m[:3]), np.array(scene.bounds_m[3:])
    assert scene.d_scene_m == pytest.approx(np.linalg.norm(hi - lo))
    assert 40.0 < scene.d_scene_m < 45.0  # 30 m x 30 m, about 5 m of relief


def test_every_start_is_collision_free(scene):
    body = RoverBody(scene, RoverConfig())
    for name, (x, y, yaw) in scene.starts.items():
        assert body.clearance(body.base_pose(x, y, yaw)) > 0.3, name


def test_collision_between_free_waypoints_is_caught(scene):
    body = RoverBody(scene, RoverConfig())
    rock = max(scene.objects[5:], key=lambda o: o.extents[0])  # a big rock
    c = rock.bounds.mean(axis=0)
    before, after = (c[0] - 4.0, c[1], 0.0), (c[0] + 4.0, c[1], 0.0)
    assert body.clearance(body.base_pose(*before)) > 0 < body.clearance(body.base_pose(*after))
    result = body.drive(before, [after])
    assert result.collided and result.executed_fraction < 0.7
    assert body.clearance(body.base_pose(*result.final_xy_yaw)) > 0  # stopped before it


@pytest.fixture(scope="module")
def sim(scene):
    cfg = MissionConfig()
    s = RoverSim(cfg, scene)
    yield s
    s.close()


def test_depth_back_projects_onto_the_true_surface(sim, scene):
    frame = sim.render(0)
    assert frame.depth_m.dtype == np.float32 and frame.depth_m.shape == (120, 160)
    valid = np.isfinite(frame.depth_m)
    assert 0.5 < valid.mean() < 1.0  # the sky has no return
    pts = backproject(frame.depth_m, frame.intrinsics, frame.T_map_camera.matrix())
    truth = scene.surface_samples(200_000, seed=1)
    from scipy.spatial import cKDTree
    d, _ = cKDTree(truth).query(pts)
    assert np.median(d) < 0.1


def test_executing_a_path_moves_the_rover(sim):
    x, y, yaw = sim.state
    path = PlanPath(0, [Pose.from_xyz_yaw(x, y, 0, yaw), Pose.from_xyz_yaw(x + 1.0, y, 0, yaw)])
    report = sim.execute(path)
    assert not report.collided and report.path_length_m == pytest.approx(1.0)
    assert sim.state[0] == pytest.approx(x + 1.0)
    assert report.min_clearance_m > 0


def _depths(load, scene, seed: int, n: int) -> np.ndarray:
    """(n, 120, 160) depth buffers of ``scene`` put into a fresh world by ``load(client,
    scene)``, from ``n`` random eyes."""
    from rover_sim.bullet import pb
    c = pb.connect(pb.DIRECT)
    load(c, scene)
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(n):
        eye = [rng.uniform(-10, 10), rng.uniform(-10, 10), rng.uniform(1, 4)]
        view = pb.computeViewMatrix(eye, [eye[0] + 3, eye[1] - 1, 0.0], [0, 0, 1],
                                    physicsClientId=c)
        proj = pb.computeProjectionMatrixFOV(60, 4 / 3, 0.05, 30, physicsClientId=c)
        out.append(np.asarray(pb.getCameraImage(
            160, 120, view, proj, renderer=pb.ER_TINY_RENDERER, physicsClientId=c)[3]))
    pb.disconnect(c)
    return np.stack(out)


def test_the_scene_renders_the_same_from_files_and_worlds_do_not_accumulate():
    """pybullet keeps every vertex list it is given; the scene goes in as OBJ files instead,
    and renders to the same depth, to the bit, as from lists. Worlds made and closed one
    after another (a study worker's missions) then keep no memory."""
    from rover_sim.bullet import pb
    from rover_sim.world import add_scene

    scene = build_arch_field()

    def from_lists(client, scene):
        for mesh, rgba in scene.visual_meshes:
            if len(mesh.faces):
                vis = pb.createVisualShape(pb.GEOM_MESH, vertices=mesh.vertices.tolist(),
                                           indices=mesh.faces.ravel().tolist(),
                                           rgbaColor=rgba, physicsClientId=client)
                pb.createMultiBody(baseMass=0, baseVisualShapeIndex=vis,
                                   physicsClientId=client)

    assert np.array_equal(_depths(add_scene, scene, 1, 6), _depths(from_lists, scene, 1, 6))

    import gc
    sizes = []
    for _ in range(12):
        c = pb.connect(pb.DIRECT)
        add_scene(c, scene)
        pb.disconnect(c)
        gc.collect()
        sizes.append(sum(isinstance(o, list) for o in gc.get_objects()))
    # From lists pybullet kept about 11,700 of them a world (arch_field's vertices).
    assert sizes[-1] - sizes[3] < 100, sizes


def test_a_mesh_over_pybullets_index_limit_goes_in_as_pieces_that_render_the_same(
        monkeypatch):
    # pybullet drops the indices of one mesh beyond 524,288 (a long traverse's terrain and
    # rocks come near it): add_scene gives it a large mesh in runs of faces. Here the runs are
    # made small, so that arch_field's own meshes go in as many pieces; the depth is the same.
    from rover_sim import world
    from rover_sim.world import _pieces, add_scene
    scene = build_arch_field()

    whole = _depths(add_scene, scene, 2, 4)
    monkeypatch.setattr(world, "MAX_SHAPE_FACES", 1000)
    terrain = scene.terrain
    pieces = _pieces(terrain)
    assert len(pieces) == -(-len(terrain.faces) // 1000)
    assert np.array_equal(np.concatenate([p.triangles for p in pieces]), terrain.triangles)
    assert np.array_equal(_depths(add_scene, scene, 2, 4), whole)
