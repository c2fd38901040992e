"""Degraded sensing statistics, pose drift, the rover's limits and the flyer platform."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from scipy.ndimage import label

from mission.runtime.loop import run_in_process
from mission.scoring.coverage import CoverageEvaluator
from planner.planner import make_planner
from rover_sim.flyer import FlyerBody
from rover_sim.rover import RoverBody
from rover_sim.scene import Scene
from rover_sim.sensing import Sensing, incidence_cos
from rover_sim.sim import RoverSim
from rovergate.config import FlyerConfig, MissionConfig, RoverConfig, SensingConfig
from rovergate.types import PLANNER_DTYPE, PlannerMap, PlanPath, Pose, make_cloud


@pytest.fixture(scope="module")
def clean_frame(scene):
    sim = RoverSim(MissionConfig(), scene)
    frame = sim.render(0)
    sim.close()
    return frame


def test_depth_noise_is_range_proportional(clean_frame):
    s = Sensing(SensingConfig(noise_frac=0.02), seed=3)
    clean = clean_frame.depth_m
    noisy = s.degrade(clean, clean_frame.intrinsics, step=1)
    ok = np.isfinite(clean)
    rel = (noisy[ok] - clean[ok]) / clean[ok]
    assert np.std(rel) == pytest.approx(0.02, rel=0.08)
    assert abs(np.mean(rel)) < 0.002
    # Far returns get larger errors than near ones.
    err = np.abs(noisy[ok] - clean[ok])
    near, far = clean[ok] < np.median(clean[ok]), clean[ok] >= np.median(clean[ok])
    assert err[far].mean() > 1.5 * err[near].mean()


def test_blob_dropout_removes_the_set_share_in_blobs(clean_frame):
    s = Sensing(SensingConfig(dropout_blob_frac=0.1, dropout_blob_px=4.0), seed=5)
    lost = s.dropout_mask(clean_frame.depth_m.shape, np.random.default_rng(0))
    assert lost.mean() == pytest.approx(0.1, abs=0.005)
    _, n_blobs = label(lost)
    assert lost.sum() / n_blobs > 20  # structured: tens of pixels per blob, not single pixels
    ok = np.isfinite(clean_frame.depth_m)
    rates = [np.isnan(s.degrade(clean_frame.depth_m, clean_frame.intrinsics, t)[ok]).mean()
             for t in range(30)]
    assert np.mean(rates) == pytest.approx(0.1, abs=0.02)


def test_pixel_dropout_rate(clean_frame):
    s = Sensing(SensingConfig(dropout_pixel_prob=0.05), seed=5)
    rates = [np.isnan(s.degrade(clean_frame.depth_m, clean_frame.intrinsics, t))
             [np.isfinite(clean_frame.depth_m)].mean() for t in range(5)]
    assert np.mean(rates) == pytest.approx(0.05, abs=0.005)


def test_grazing_returns_are_dropped(clean_frame):
    limit = 70.0
    s = Sensing(SensingConfig(grazing_max_deg=limit), seed=1)
    clean = clean_frame.depth_m
    out = s.degrade(clean, clean_frame.intrinsics, step=0)
    cos = incidence_cos(clean, clean_frame.intrinsics)
    kept = np.isfinite(out) & np.isfinite(cos)
    assert np.all(cos[kept] >= np.cos(np.radians(limit)) - 1e-6)
    dropped = np.isfinite(clean) & np.isnan(out)
    assert 0.01 < dropped.mean() < 0.9  # the far ground is grazing from a 1.6 m mast


def test_degradation_is_seeded(clean_frame):
    cfg = SensingConfig(noise_frac=0.01, dropout_blob_frac=0.05, dropout_pixel_prob=0.01)
    a = Sensing(cfg, 7).degrade(clean_frame.depth_m, clean_frame.intrinsics, 4)
    b = Sensing(cfg, 7).degrade(clean_frame.depth_m, clean_frame.intrinsics, 4)
    c = Sensing(cfg, 8).degrade(clean_frame.depth_m, clean_frame.intrinsics, 4)
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(np.nan_to_num(a), np.nan_to_num(c))
    off = Sensing(SensingConfig(), 7).degrade(clean_frame.depth_m, clean_frame.intrinsics, 4)
    assert off is clean_frame.depth_m  # all off by default: untouched


def test_drift_is_a_seeded_random_walk_with_the_set_step():
    s = Sensing(SensingConfig(drift_xy_m=0.02, drift_yaw_deg=0.5), seed=11)
    walk = np.array([s.drift_at(t) for t in range(3001)])
    inc = np.diff(walk, axis=0)
    assert np.std(inc[:, 0]) == pytest.approx(0.02, rel=0.08)
    assert np.std(inc[:, 1]) == pytest.approx(0.02, rel=0.08)
    assert np.all(inc[:, 2] == 0)  # no z drift configured
    assert np.degrees(np.std(inc[:, 3])) == pytest.approx(0.5, rel=0.08)
    again = Sensing(SensingConfig(drift_xy_m=0.02, drift_yaw_deg=0.5), seed=11)
    np.testing.assert_array_equal(again.drift_at(3000), walk[3000])


def test_drift_moves_the_published_pose_not_the_true_one(scene):
    cfg = MissionConfig()
    cfg.sensing = SensingConfig(drift_xy_m=0.05, drift_yaw_deg=1.0)
    sim = RoverSim(cfg, scene)
    clean = RoverSim(MissionConfig(), scene)
    try:
        for t in range(4):
            f, g = sim.render(t), clean.render(t)
            np.testing.assert_array_equal(f.depth_m, g.depth_m)  # rendered from the true pose
            d = sim.sensing.drift_at(t)
            np.testing.assert_allclose(f.T_map_base.position - g.T_map_base.position, d[:3],
                                       atol=1e-9)
            # Commands are carried out in the rover's believed frame: "stay where I think I
            # am" keeps the true pose.
            report = sim.execute(PlanPath(t, [f.T_map_base]))
            clean.execute(PlanPath(t, [g.T_map_base]))
            assert report.pose_error_m == pytest.approx(np.linalg.norm(sim.sensing.drift_at(
                t + 1)[:3]))
            assert sim.state == pytest.approx(clean.state)
    finally:
        sim.close()
        clean.close()


def test_rover_stops_before_untraversable_ground():
    # Flat ground up to x = 3 m, then a 40-degree slope; and a 0.5 m ledge across y = 6 m.
    xs = np.arange(-10.0, 10.01, 0.25)
    X, Y = np.meshgrid(xs, xs)
    Z = np.where(X > 3.0, (X - 3.0) * np.tan(np.radians(40)), 0.0)
    Z = np.where((Y > 6.0) & (X < 3.0), 0.5, Z)
    scene = Scene("ramp", xs, xs.copy(), Z, [], (-8, -8, 0, 8, 8, 2))
    body = RoverBody(scene, RoverConfig())
    up_slope = body.drive((0.0, 0.0, 0.0), [(6.0, 0.0, 0.0)])
    assert up_slope.untraversable and not up_slope.collided
    x_stop = up_slope.final_xy_yaw[0]
    assert 2.0 < x_stop < 3.0  # the front wheels stop at the foot of the slope
    up_step = body.drive((0.0, 0.0, np.pi / 2), [(0.0, 8.0, np.pi / 2)])
    assert up_step.untraversable and 5.0 < up_step.final_xy_yaw[1] < 6.0
    along = body.drive((0.0, 0.0, np.pi / 2), [(0.0, -5.0, np.pi / 2)])
    assert not along.untraversable and along.executed_fraction == 1.0


def test_flyer_collision_between_free_waypoints_is_caught(scene):
    fly = FlyerBody(scene, FlyerConfig(), 0.05)
    rock = max(scene.objects[5:], key=lambda o: o.extents[0])
    c = rock.bounds.mean(axis=0)
    z = float(c[2])
    a, b = (c[0] - 4.0, c[1], z, 0.0, 0.0), (c[0] + 4.0, c[1], z, 0.0, 0.0)
    assert fly.clearance(a[:3]) > 0 and fly.clearance(b[:3]) > 0
    result = fly.drive(a, [b])
    assert result.collided and result.executed_fraction < 0.7
    assert fly.clearance(result.final_xy_yaw[:3]) > 0


def test_flyer_planner_plans_in_position_and_view_direction(scene):
    cfg = MissionConfig(platform="flyer")
    cfg.scene.bounds_m, cfg.scene.d_scene_m = scene.bounds_m, scene.d_scene_m
    planner = make_planner(cfg)
    # A flat floor of points and a wall ahead: the flyer must keep its sphere off both.
    g = np.mgrid[-10:10:0.2, -10:10:0.2].reshape(2, -1).T
    floor = np.c_[g, np.zeros(len(g))]
    wall = np.c_[np.full(200, 3.0), np.repeat(np.linspace(-5, 5, 20), 10),
                 np.tile(np.linspace(0, 4, 10), 20)]
    pts = np.vstack([floor, wall]).astype(np.float32)
    occ = PlannerMap(0, make_cloud(pts, PLANNER_DTYPE, source=0, views=1))
    here = Pose.from_xyz_yaw_pitch(0.0, 0.0, 1.6, 0.0, -0.3)
    result = planner.plan(0, occ, here)
    assert result.reason in ("best-feasible", "rotate")
    poses = result.path.poses
    assert np.allclose(poses[0].position, here.position)
    from scipy.spatial import cKDTree
    tree = cKDTree(pts)
    for p in poses[1:]:
        assert tree.query(p.position)[0] > cfg.flyer.radius_m
        assert cfg.flyer.min_altitude_m - 1e-6 <= p.position[2] <= cfg.flyer.max_altitude_m
    pitches = [p.pitch for p in poses]
    assert min(pitches) >= np.radians(cfg.flyer.min_pitch_deg) - 1e-6


def test_flyer_mission_runs_and_is_reproducible(tmp_path):
    from rover_sim.catalog import resolve_scene
    cfg = MissionConfig(platform="flyer", steps=6, progress=False, scene=dataclasses.replace(
        MissionConfig().scene, name="ruins"))
    resolve_scene(cfg.scene)
    a, b = run_in_process(cfg), run_in_process(cfg)
    assert a.coverage == b.coverage and a.coverage[-1] > a.coverage[0] > 0
    assert sum(e.path_length_m for e in a.executions) > 1.0


def test_coverage_update_matches_brute_force():
    rng = np.random.default_rng(0)
    samples = rng.uniform(0, 10, (20_000, 3)).astype(np.float32)
    surface = rng.uniform(0, 10, (3000, 3)).astype(np.float32)
    ev = CoverageEvaluator(samples, 0.3)
    for k in (1000, 2000, 3000):
        ev.update(surface[:k])
    d = np.min(np.linalg.norm(samples[:, None, :] - surface[None, ::1, :], axis=2), axis=1)
    assert ev.fraction == pytest.approx(np.mean(d <= 0.3))


def test_render_returns_when_the_eye_lies_in_a_face_plane():
    """TinyRenderer hung when the eye sat exactly in the plane of an axis-aligned face (the
    flyer at the lava tube's mouth, x = 0, looking along +y); run it in a child with a limit."""
    import subprocess
    import sys
    code = ("import numpy as np\n"
            "from rovergate.config import MissionConfig, SceneConfig\n"
            "from rover_sim.catalog import resolve_scene\n"
            "from rover_sim.sim import RoverSim\n"
            "cfg = MissionConfig(scene=SceneConfig(name='lava_tube'), platform='flyer')\n"
            "resolve_scene(cfg.scene)\n"
            "sim = RoverSim(cfg)\n"
            "s = list(sim.state); s[:2] = [0.0, 0.0]; s[3] = np.pi / 2; sim.state = tuple(s)\n"
            "print(np.isfinite(sim.render(0).depth_m).mean())\n")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr[-2000:]
    assert float(r.stdout.strip().splitlines()[-1]) > 0.3
