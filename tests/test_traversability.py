"""The rover's traversability layer on built cases, rendered by pybullet: what its hazard
cameras see, and the motions it refuses (planner/traversability.py)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import trimesh

from planner.planner import GreedyPlanner
from planner.platforms import RoverModel
from planner.traversability import BELLY, UNKNOWN, WHEEL_DROP, TerrainMap, driven_way
from rover_sim.scene import Scene
from rover_sim.sim import RoverSim
from rovergate.config import MissionConfig
from rovergate.geometry import densify_se2, hazcam_from_base
from rovergate.types import (
    PLANNER_DTYPE,
    ExecutionReport,
    PlannerMap,
    PlanPath,
    Pose,
    Source,
    make_cloud,
    xyz,
)

BOUNDS = (-8.0, -8.0, -4.0, 8.0, 8.0, 4.0)


def built(name: str, height=lambda x, y: 0.0 * x, objects=()) -> tuple[MissionConfig, RoverSim]:
    """A flat (or shaped) built world with the rover at the origin facing +x."""
    xs = np.arange(-10.0, 10.01, 0.1)
    X, Y = np.meshgrid(xs, xs)
    scene = Scene(name, xs, xs, height(X, Y), list(objects), BOUNDS, {"a": (0.0, 0.0, 0.0)})
    cfg = MissionConfig()
    cfg.scene.name = name
    cfg.scene.bounds_m = BOUNDS
    cfg.scene.d_scene_m = scene.d_scene_m
    return cfg, RoverSim(cfg, scene)


def sensed(cfg: MissionConfig, sim: RoverSim, poses=((0.0, 0.0, 0.0),)) -> TerrainMap:
    """The layer after the rover stood and looked at each of ``poses`` (its trail)."""
    terrain = TerrainMap(cfg)
    for step, pose in enumerate(poses):
        sim.state = pose
        frame = sim.render(step)
        terrain.add_step(step, frame.T_map_base.matrix(),
                         (frame.T_map_camera.matrix(), frame.intrinsics, frame.depth_m),
                         frame.hazcams)
    x, y, _ = poses[-1]
    terrain.prepare(x, y)
    return terrain


def straight(x1: float, y1: float = 0.0, start=(0.0, 0.0, 0.0)) -> list[tuple]:
    return [start, (x1, y1, start[2])]


def test_the_hazard_cameras_see_the_ground_the_mast_cannot():
    cfg, sim = built("flat")
    try:
        frame = sim.render(0)
        assert set(frame.hazcams) == {"front", "rear"}
        for depth in frame.hazcams.values():
            assert depth.shape == (cfg.hazcam.height_px, cfg.hazcam.width_px)
            # The lowest rows look straight down from 0.8 m at 45 degrees off the axis.
            assert np.nanmin(depth) == pytest.approx(0.8 * np.cos(np.radians(45)), abs=0.02)
        terrain = sensed(cfg, sim)
        # The ground from the body's edge to 2 m ahead and behind: known (the mast's view of
        # the ground begins about 2 m out).
        for x in (0.7, 1.2, 1.8, -0.7, -1.8):
            i, j = terrain._cells(np.array([[x, 0.0]]))
            assert np.isfinite(terrain.top[i[0], j[0]]), x
    finally:
        sim.close()


def test_a_drop_off_the_mast_camera_cannot_see_is_refused():
    # A 3 m cliff 2 m ahead: beyond its edge, the ground is hidden from the mast and out of
    # the hazard camera's range. The sim would stop the rover at the edge; the layer must
    # not send it there.
    cfg, sim = built("cliff", height=lambda x, y: np.where(x > 2.0, -3.0, 0.0))
    try:
        terrain = sensed(cfg, sim)
        assert terrain.admit(straight(0.8)) is None  # seen ground ahead: drivable
        assert terrain.admit(straight(2.6)) == UNKNOWN
        assert terrain.admit(straight(4.0)) == UNKNOWN
        assert not terrain.free(2.6, 0.0, 0.0)
        assert terrain.refused[UNKNOWN] == 2
        # The rover at the origin, the edge in its hazard camera: the planner's model keeps it
        # on this side.
        model = RoverModel(cfg, np.zeros((0, 3), np.float32), Pose.from_xyz_yaw(0, 0, 0, 0),
                           terrain=terrain)
        assert model.is_free((1.0, 0.0, 0.0)) and not model.is_free((2.7, 0.0, 0.0))
    finally:
        sim.close()


def test_a_predicted_only_floor_is_not_drivable():
    cfg, sim = built("flat")
    try:
        terrain = sensed(cfg, sim)
        # A predicted floor over ground no camera has seen yet (6 m to the left), and the
        # observed floor around the rover: the map alone would drive onto the prediction.
        xs, ys = np.meshgrid(np.arange(-1.0, 1.0, 0.15), np.arange(4.5, 7.5, 0.15))
        predicted = np.c_[xs.ravel(), ys.ravel(), np.zeros(xs.size)].astype(np.float32)
        xs, ys = np.meshgrid(np.arange(-1.0, 3.0, 0.15), np.arange(-1.0, 1.0, 0.15))
        observed = np.c_[xs.ravel(), ys.ravel(), np.zeros(xs.size)].astype(np.float32)
        points = np.vstack([observed, predicted])
        source = np.r_[np.zeros(len(observed), bool), np.ones(len(predicted), bool)]
        here = Pose.from_xyz_yaw(0, 0, 0, 0)
        with_layer = RoverModel(cfg, points, here, predicted=source, terrain=terrain)
        map_only = RoverModel(cfg, points, here, predicted=source)
        on_prediction = (0.0, 6.0, np.pi / 2)
        assert map_only.is_free(on_prediction)
        assert not with_layer.is_free(on_prediction)
        assert terrain.assess(*on_prediction) == UNKNOWN
        assert with_layer.is_free((1.2, 0.0, 0.0))  # the observed floor ahead is drivable
    finally:
        sim.close()


def test_a_rock_under_the_belly_is_refused_and_a_pebble_is_not():
    rock = trimesh.creation.box(extents=[0.3, 0.3, 0.3])
    rock.apply_translation([1.6, 0.0, 0.15])
    pebble = trimesh.creation.box(extents=[0.2, 0.2, 0.1])
    pebble.apply_translation([-1.6, 0.0, 0.05])
    cfg, sim = built("rock", objects=[rock, pebble])
    try:
        # Seen from both sides (from one, its far side is in its own shadow: unknown).
        terrain = sensed(cfg, sim, [(3.6, 0.0, np.pi), (-3.6, 0.0, 0.0), (0.0, 0.0, 0.0)])
        # The rock, 0.3 m tall (the clearance is 0.25 m), under the body's centre: refused.
        over_rock = (1.6, 0.0, 0.0)
        assert terrain.assess(*over_rock) == BELLY
        assert terrain.admit(straight(1.6)) in (BELLY, WHEEL_DROP)
        # ... and the true scene agrees: driving there hits the rock.
        assert sim.body.drive((0.0, 0.0, 0.0), [over_rock]).collided
        # A 0.1 m pebble under the belly, between the wheels (behind the rover): passes.
        assert terrain.assess(-1.6, 0.0, 0.0) is None
        assert not sim.body.drive((0.0, 0.0, 0.0), [(-1.6, 0.0, 0.0)]).collided
    finally:
        sim.close()


def test_a_rover_walled_in_by_predictions_backs_out_the_way_it_came():
    cfg, sim = built("flat")
    try:
        trail = [(-3.0, 0.0, 0.0), (-2.0, 0.0, 0.0), (-1.0, 0.0, 0.0), (0.0, 0.0, 0.0)]
        terrain = sensed(cfg, sim, trail)
        # Observed floor all round; a predicted wall in the body's height band on a ring 0.72 m
        # from the rover: no candidate and no turn is free on the map.
        xs, ys = np.meshgrid(np.arange(-6.0, 6.0, 0.15), np.arange(-6.0, 6.0, 0.15))
        floor = np.c_[xs.ravel(), ys.ravel(), np.zeros(xs.size)]
        a = np.linspace(-np.pi, np.pi, 120, endpoint=False)
        ring = np.concatenate([np.c_[0.72 * np.cos(a), 0.72 * np.sin(a), np.full(a.size, z)]
                               for z in (0.4, 0.6, 0.8)])
        cloud = make_cloud(np.vstack([floor, ring]).astype(np.float32), PLANNER_DTYPE,
                           source=np.r_[np.full(len(floor), Source.OBSERVED),
                                        np.full(len(ring), Source.PREDICTED)], views=5)
        result = GreedyPlanner(cfg).plan(5, PlannerMap(5, cloud), Pose.from_xyz_yaw(0, 0, 0, 0),
                                         terrain=terrain)
        assert result.reason == "backout"
        end = result.path.poses[-1].position
        # Back along the trail (heading kept: it reverses), as far as the motion budget.
        assert end[0] == pytest.approx(-cfg.planner.max_step_m, abs=0.05)
        assert abs(end[1]) < 1e-6 and abs(result.path.poses[-1].yaw) < 1e-6
        # Without a trail (a rover that has not moved) there is nothing to back along.
        fresh = sensed(cfg, sim)
        stay = GreedyPlanner(cfg).plan(0, PlannerMap(0, cloud), Pose.from_xyz_yaw(0, 0, 0, 0),
                                       terrain=fresh)
        assert stay.reason == "stay"
    finally:
        sim.close()


def test_a_rover_backs_out_along_the_way_it_drove_not_straight_to_its_last_stop():
    # It drove from A round a rock by W to C; the straight line from C back to A crosses
    # the rock. Its last path (A, W, C), as far as the execution got, is its way back.
    rock = trimesh.creation.box(extents=[0.4, 0.4, 0.4])
    rock.apply_translation([-1.5, 0.0, 0.2])
    cfg, sim = built("detour", objects=[rock])
    A, W, C = (-3.0, 0.0, 0.0), (-1.5, 2.0, 0.0), (0.0, 0.0, 0.0)
    try:
        terrain = TerrainMap(cfg)
        for step, (pose, way) in enumerate([(A, []), (C, [W])]):
            for looked in ([pose] if not way else [*way, pose]):  # what it saw on the way
                sim.state = looked
                frame = sim.render(step)
                if looked is pose:
                    terrain.add_step(step, frame.T_map_base.matrix(),
                                     (frame.T_map_camera.matrix(), frame.intrinsics,
                                      frame.depth_m), frame.hazcams, way)
                else:
                    terrain.add_frame(step, frame.T_map_camera.matrix(), frame.intrinsics,
                                      frame.depth_m, cfg.traverse.mast_range_m)
                    for end, depth in frame.hazcams.items():
                        terrain.add_frame(step, hazcam_from_base(frame.T_map_base.matrix(),
                                                                 cfg.hazcam, end),
                                          terrain.hazcam_k, depth, cfg.hazcam.max_range_m)
        terrain.prepare(*C[:2])
        path = PlanPath(0, [Pose.from_xyz_yaw(*q[:2], 0.0, q[2]) for q in (A, W, C)])
        # The way as driven: all of it, or as far as the bumper let it get.
        done = ExecutionReport(0, False, 0, 1.0, 4.0, 1.0)
        assert [q[:3] for q in driven_way(path, done)] == [pytest.approx(W)]
        assert driven_way(path, dataclasses.replace(done, executed_fraction=0.3)) == []
        # The straight way back crosses the rock: ACE refuses it.
        assert any(terrain.assess(*q) is not None
                   for q in densify_se2([C, A], 0.1, np.radians(5.0)))
        way = terrain.backout(C, cfg.planner.max_step_m, cfg.traverse.backout_steps)
        assert way and way[0] == pytest.approx(W)
        swept = densify_se2([C, *way], 0.1, np.radians(5.0))
        assert all(terrain.assess(*q) is None for q in swept)
        assert min(np.hypot(q[0] + 1.5, q[1]) for q in swept) > 0.9  # the rock stays aside
        # ... and the true scene agrees: the way back does not touch the rock.
        assert not sim.body.drive(C, way).collided
    finally:
        sim.close()


def test_a_rover_that_stays_put_looks_around_with_its_mast():
    # A tall box 4 m to the rover's left: out of the mast camera's view while it faces ahead.
    box = trimesh.creation.box(extents=[1.0, 1.0, 1.5])
    box.apply_translation([0.0, 4.0, 0.75])

    def heading_deg(frame) -> float:  # where the optical axis (z) points, from above
        R = frame.T_map_camera.matrix()
        return round(float(np.degrees(np.arctan2(R[1, 2], R[0, 2]))))

    def centre_depth(frame) -> float:
        h, w = frame.depth_m.shape
        return float(np.nanmedian(frame.depth_m[h // 2 - 4:h // 2 + 4, w // 2 - 4:w // 2 + 4]))

    for look_around in (True, False):
        cfg, sim = built("look", objects=[box])
        cfg.rover.look_around = look_around
        here = Pose.from_xyz_yaw(0.0, 0.0, 0.0, 0.0)
        try:
            frames = []
            for step in range(5):  # the planner stays (a one-pose path) four times
                frames.append(sim.render(step))
                if step < 4:
                    sim.execute(PlanPath(step, [here]))
            sim.execute(PlanPath(5, [here, Pose.from_xyz_yaw(0.5, 0.0, 0.0, 0.0)]))
            frames.append(sim.render(6))
            headings = [heading_deg(f) for f in frames]
            if look_around:
                # Left, right, behind, left again; forward once it drives.
                assert headings == [0, 90, -90, 180, 90, 0]
                assert centre_depth(frames[1]) < 4.0 < 5.0 < centre_depth(frames[0])
            else:
                assert headings == [0] * 6
            # The base does not turn: only the mast.
            assert all(abs(f.T_map_base.yaw) < 1e-9 for f in frames)
        finally:
            sim.close()


def floor_and(predicted: np.ndarray, hole=None) -> tuple[np.ndarray, np.ndarray]:
    """An observed floor at z = 0 around the origin (less the (xmin, ymin, xmax, ymax)
    ``hole``) and ``predicted`` points: (points, predicted flags)."""
    xs, ys = np.meshgrid(np.arange(-3.0, 3.0, 0.15), np.arange(-3.0, 3.0, 0.15))
    floor = np.c_[xs.ravel(), ys.ravel(), np.zeros(xs.size)]
    if hole is not None:
        x0, y0, x1, y1 = hole
        floor = floor[~((floor[:, 0] >= x0) & (floor[:, 0] < x1)
                        & (floor[:, 1] >= y0) & (floor[:, 1] < y1))]
    points = np.vstack([floor, predicted]).astype(np.float32)
    return points, np.r_[np.zeros(len(floor), bool), np.ones(len(predicted), bool)]


def test_a_prediction_under_the_belly_does_not_hold_the_rover_where_it_stands():
    cfg, sim = built("flat")
    try:
        terrain = sensed(cfg, sim)
        # Predicted points 0.2 m up (in the margin band under the 0.25 m belly): under the
        # body where it stands, and 1.5 m ahead.
        points, source = floor_and(np.array([[0.1, -0.2, 0.2], [1.5, 0.0, 0.2]]))
        model = RoverModel(cfg, points, Pose.from_xyz_yaw(0, 0, 0, 0), predicted=source,
                           terrain=terrain)
        assert model.is_free(model.current)  # the body stands over it: not an obstacle
        assert not model.is_free((1.5, 0.0, 0.0))  # elsewhere it still blocks
    finally:
        sim.close()


def test_measured_ground_beats_a_predicted_hole():
    cfg, sim = built("flat")
    try:
        terrain = sensed(cfg, sim)
        # One 0.5 m cell of the map's ground grid ahead (x 1.0-1.5) holds only predictions,
        # 0.35 m under the floor the hazard camera measured there: the map's own estimate
        # would read a step beyond the rover's limit.
        xs, ys = np.meshgrid(np.arange(1.05, 1.5, 0.15), np.arange(-0.45, 0.0, 0.15))
        hole = np.c_[xs.ravel(), ys.ravel(), np.full(xs.size, -0.35)]
        points, source = floor_and(hole, hole=(1.0, -0.5, 1.5, 0.0))
        here = Pose.from_xyz_yaw(0, 0, 0, 0)
        map_only = RoverModel(cfg, points, here, predicted=source)
        with_layer = RoverModel(cfg, points, here, predicted=source, terrain=terrain)
        assert not map_only.ground.traversable(1.2, 0.0, 0.0)
        assert with_layer.ground.traversable(1.2, 0.0, 0.0)
        assert with_layer.is_free((1.2, 0.0, 0.0))
    finally:
        sim.close()


def test_a_dithering_rover_tries_somewhere_else_first():
    cfg, sim = built("flat")
    try:
        # Seven steps within 0.2 m of the origin: a dither (5 steps, under 1 m net).
        poses = [(0.02 * k * (-1) ** k, 0.0, 0.0) for k in range(7)] + [(0.0, 0.0, 0.0)]
        dithered = sensed(cfg, sim, poses)
        assert len(dithered.dither_spots()) > 0
        cloud = make_cloud(floor_and(np.zeros((0, 3)))[0], PLANNER_DTYPE,
                           source=Source.OBSERVED, views=5)  # nothing novel: no gain anywhere
        here = Pose.from_xyz_yaw(0, 0, 0, 0)
        model = RoverModel(cfg, xyz(cloud), here, terrain=dithered)
        assert model.stale([(0.5, 0.0, 0.0), (2.5, 0.0, 0.0)]).tolist() == [True, False]

        def goal_distance(terrain: TerrainMap) -> float:
            result = GreedyPlanner(cfg).plan(8, PlannerMap(8, cloud), here, terrain=terrain)
            assert result.reason == "best-feasible"
            return float(np.linalg.norm(result.path.poses[-1].position[:2]))
        # Without gain the nearest candidate wins; after a dither, one beyond its radius.
        assert goal_distance(sensed(cfg, sim)) < cfg.traverse.dither_radius_m
        assert goal_distance(dithered) >= cfg.traverse.dither_radius_m
    finally:
        sim.close()


def test_a_rover_with_nothing_left_to_see_heads_away_from_where_it_has_been():
    # --planner.explore-below: no candidate has gain, so the rover that came from -x goes
    # on away from its trail (where it has not looked yet), not to the nearest candidate.
    cfg, sim = built("flat")
    try:
        trail = sensed(cfg, sim, [(x, 0.0, 0.0) for x in (-3.0, -2.0, -1.0, 0.0)])
        cloud = make_cloud(floor_and(np.zeros((0, 3)))[0], PLANNER_DTYPE,
                           source=Source.OBSERVED, views=5)  # nothing novel: no gain anywhere
        here = Pose.from_xyz_yaw(0, 0, 0, 0)

        def goal(explore_below: int) -> np.ndarray:
            cfg.planner.explore_below = explore_below
            result = GreedyPlanner(cfg).plan(4, PlannerMap(4, cloud), here, terrain=trail)
            assert result.reason == "best-feasible" and result.gain == 0
            return result.path.poses[-1].position[:2]
        nearest, onwards = goal(0), goal(1)
        model = RoverModel(cfg, xyz(cloud), here, terrain=trail)
        away = model.away([(*nearest, 0.0), (*onwards, 0.0)])
        assert np.linalg.norm(nearest) < 1.0 and away[0] < 1.0
        assert away[1] > 1.5 and onwards[0] > 1.0  # ahead, beyond where it stood
    finally:
        sim.close()


def test_densify_keeps_spacing_and_turn_limits():
    poses = densify_se2([(0.0, 0.0, 0.0), (1.0, 0.0, np.pi / 2)], 0.1, np.radians(5))
    xy = np.array([p[:2] for p in poses])
    assert np.linalg.norm(np.diff(xy, axis=0), axis=1).max() <= 0.1 + 1e-9
    assert np.abs(np.diff([p[2] for p in poses])).max() <= np.radians(5) + 1e-9
    assert poses[-1] == pytest.approx((1.0, 0.0, np.pi / 2))


@pytest.mark.e2e
def test_the_rover_drives_a_rocky_site_of_its_own_mesh_without_touching_a_rock(tmp_path):
    """The issue's bar: `rovergate run --platform rover --condition learned --steps 60` on a
    mesh file of a rocky site (examples/rocky_site.py writes one): no collision, and the
    rover gets somewhere (not stuck in place)."""
    import subprocess
    import sys
    from pathlib import Path

    from tests.conftest import read_metrics, run_cli
    site = tmp_path / "rocky_site.ply"
    example = Path(__file__).resolve().parents[1] / "examples" / "rocky_site.py"
    subprocess.run([sys.executable, str(example), str(site), "--seed", "1"], check=True,
                   timeout=120)
    out = tmp_path / "run"
    r = run_cli("run", "--platform", "rover", "--condition", "learned", "--steps", "60",
                "--scene", str(site), "--in-process", "--no-record", "--out", str(out))
    assert r.returncode == 0, r.stderr[-3000:]
    m = read_metrics(out)
    assert m["collisions"] == 0 and m["min_clearance_m"] > 0
    assert m["path_length_m"] >= 20.0 and m["stuck_steps"] <= 10
