"""Planner pieces: gain with occlusion, FCL against the map, OMPL in SE(2), determinism."""

from __future__ import annotations

import numpy as np
import pytest

from planner.collision import OccupancyCollisionModel
from planner.gain import GainField, render_gain, visible_mask
from planner.motion import path_length, plan_se2
from planner.planner import BeamPlanner, GreedyPlanner, novel_mask
from rovergate.config import MissionConfig, RoverConfig
from rovergate.geometry import R_BODY_OPTICAL
from rovergate.types import PLANNER_DTYPE, CameraIntrinsics, PlannerMap, Pose, Source, make_cloud

K = CameraIntrinsics.from_fov(40, 30, 45.0)
BOUNDS = (-10.0, -10.0, -1.0, 10.0, 10.0, 5.0)


def cam(x=0.0):
    T = np.eye(4)
    T[:3, :3] = R_BODY_OPTICAL
    T[:3, 3] = [x, 0, 1]
    return T


def grid_wall(x, n=20, size=2.0):
    ys, zs = np.meshgrid(np.linspace(-size, size, n), np.linspace(1 - size, 1 + size, n))
    return np.c_[np.full(n * n, x), ys.ravel(), zs.ravel()].astype(np.float32)


def test_a_wall_hides_what_is_behind_it():
    front, back = grid_wall(5.0), grid_wall(8.0)
    vis = visible_mask(np.vstack([front, back]), cam(), K, 0.3, 20.0, 0.3)
    assert vis[: len(front)].mean() > 0.9
    assert vis[len(front):].mean() < 0.05


def test_gain_counts_only_novel_visible_points():
    pts = grid_wall(5.0)
    novel = np.zeros(len(pts), dtype=bool)
    novel[:50] = True
    gains = render_gain(pts, novel, [cam(), cam(-30.0)], K, 0.3, 20.0, 0.3, voxel_m=0.05)
    assert gains[0] == 50 and gains[1] == 0  # second camera is out of range


def test_gain_primitives_gather_points_and_count_each_once_along_a_trajectory():
    pts = grid_wall(5.0)  # 20 x 20 points 0.21 m apart
    novel = np.ones(len(pts), dtype=bool)
    field = GainField(pts, novel, 1.0, K, 0.3, 20.0, 0.3)
    assert len(field) < len(pts) and field.weight.sum() == len(pts)
    vis = field.visible(cam())
    assert field.gain(vis) == len(pts)
    seen = np.zeros(len(field), dtype=bool)
    seen[vis] = True
    assert field.gain(field.visible(cam(1.0)), seen) == 0  # the next view sees nothing new


def flat_ground(extra=None):
    xs, ys = np.meshgrid(np.arange(-10, 10, 0.2), np.arange(-10, 10, 0.2))
    pts = np.c_[xs.ravel(), ys.ravel(), np.zeros(xs.size)]
    if extra is not None:
        pts = np.vstack([pts, extra])
    return pts.astype(np.float32)


def box_points(cx, cy, z0, z1, half=0.5):
    g = np.arange(-half, half + 1e-6, 0.1)
    x, y, z = np.meshgrid(cx + g, cy + g, np.arange(z0, z1 + 1e-6, 0.1))
    return np.c_[x.ravel(), y.ravel(), z.ravel()]


def model(points):
    return OccupancyCollisionModel(points, RoverConfig(), BOUNDS, 0.5, 0.15, 0.0)


def test_collision_model_blocks_rocks_and_passes_under_overhangs():
    rock = box_points(3.0, 0.0, 0.0, 0.6)
    lintel = box_points(-3.0, 0.0, 2.5, 3.0)  # far above the body's top
    m = model(flat_ground(np.vstack([rock, lintel])))
    assert not m.is_free(3.0, 0.0, 0.0)
    assert m.is_free(-3.0, 0.0, 0.3)
    assert m.is_free(0.0, 0.0, 0.0)


def test_ompl_plans_around_an_obstacle_within_budget():
    wall = np.vstack([box_points(0.0, y, 0.0, 0.8) for y in np.arange(-3, 3.1, 1.0)])
    m = model(flat_ground(wall))
    path = plan_se2((-2.0, 0.0, 0.0), (2.0, 0.0, 0.0), m.is_free, (-10, -10, 10, 10), seed=3,
                    max_checks=20000)
    assert path is not None
    assert path[0][:2] == (-2.0, 0.0) and path[-1][:2] == (2.0, 0.0)
    assert path_length(path) > 4.0  # it had to go round
    dense = [tuple(np.add(a, f * np.subtract(b, a))) for a, b in zip(path[:-1], path[1:],
                                                                     strict=True)
             for f in np.linspace(0, 1, 20)]
    assert all(m.is_free(*p) for p in dense)


def test_ompl_is_deterministic_for_a_seed():
    m = model(flat_ground(box_points(0.0, 0.0, 0.0, 0.8, half=1.0)))
    a = plan_se2((-3.0, 0.0, 0.0), (3.0, 0.5, 1.0), m.is_free, (-10, -10, 10, 10), 5, 5000)
    b = plan_se2((-3.0, 0.0, 0.0), (3.0, 0.5, 1.0), m.is_free, (-10, -10, 10, 10), 5, 5000)
    assert a == b


def test_novelty_is_one_rule_for_every_source():
    pts = np.array([[0, 0, 0], [5, 0, 0], [0, 0, 0.1], [9, 9, 9], [1, 1, 1], [2, 2, 2]],
                   dtype=np.float32)
    cloud = make_cloud(pts, PLANNER_DTYPE,
                       source=[Source.OBSERVED, Source.OBSERVED, Source.PREDICTED,
                               Source.PREDICTED, Source.TRUTH, Source.TRUTH],
                       views=[3, 1, 2, 0, 5, 1])
    novel = novel_mask(PlannerMap(0, cloud), observed_min_views=2)
    # Seen in 2 frames or more: no longer novel, whatever the point's source.
    assert novel.tolist() == [False, True, False, True, False, True]


@pytest.mark.parametrize("planner", [GreedyPlanner, BeamPlanner])
def test_planners_move_towards_novel_points_and_are_deterministic(planner):
    cfg = MissionConfig()
    cfg.scene.bounds_m = BOUNDS
    cfg.scene.d_scene_m = 30.0
    ground = flat_ground()
    target = grid_wall(6.0, size=1.5)
    pts = np.vstack([ground, target])
    src = np.r_[np.zeros(len(ground)), np.full(len(target), Source.PREDICTED)]
    occ = PlannerMap(0, make_cloud(pts, PLANNER_DTYPE, source=src.astype(np.uint8),
                                   views=np.r_[np.full(len(ground), 5), np.zeros(len(target))]))
    here = Pose.from_xyz_yaw(0.0, 0.0, 0.0, np.pi)  # facing away from the target
    a = planner(cfg).plan(0, occ, here)
    b = planner(cfg).plan(0, occ, here)
    assert a.reason == "best-feasible" and a.gain > 0
    assert [p.position.tolist() for p in a.path.poses] == [p.position.tolist()
                                                          for p in b.path.poses]
    end = a.path.poses[-1]
    assert abs(np.cos(end.yaw)) > 0.3 and np.cos(end.yaw) > 0  # now looks towards +x


@pytest.mark.parametrize("planner", [GreedyPlanner, BeamPlanner])
def test_the_points_a_chosen_view_counts_are_its_rendered_gain(planner):
    # What the planner reports of its chosen view (TraverseReport.gain_points, from the field
    # it rendered) is the field built afresh for that view: the evaluation weighs a decision
    # with the planner's own figure, and a planner that reports none gets the same.
    from planner.planner import counted_points, gain_field
    from rovergate.geometry import camera_from_base
    from rovergate.types import Channel
    cfg = MissionConfig()
    cfg.scene.bounds_m = BOUNDS
    cfg.scene.d_scene_m = 30.0
    ground, target = flat_ground(), grid_wall(6.0, size=1.5)
    pts = np.vstack([ground, target, grid_wall(-6.0, size=1.5)])
    rng = np.random.default_rng(5)
    channels = rng.choice([Channel.GAIN, Channel.COLLISION, Channel.BOTH], len(pts))
    occ = PlannerMap(0, make_cloud(pts, PLANNER_DTYPE, views=rng.integers(0, 4, len(pts)),
                                   channels=channels.astype(np.uint8)))
    planning = planner(cfg)
    result = planning.plan(0, occ, Pose.from_xyz_yaw(0.0, 0.0, 0.0, 0.3))
    goal = result.path.poses[-1]
    reported = counted_points(cfg, occ, goal, planning.rendered)
    assert np.array_equal(reported, counted_points(cfg, occ, goal))  # built afresh
    serving = np.flatnonzero(channels & Channel.GAIN)
    attracting = occ.serving(Channel.GAIN)
    field = gain_field(cfg, pts[serving], novel_mask(attracting, cfg.planner.observed_min_views))
    cam = camera_from_base(goal.matrix(), cfg.sensor, cfg.platform)
    assert len(reported) == field.gain(field.visible(cam)) > 0
    assert set(reported) <= set(serving) and (occ.points["views"][reported] <
                                              cfg.planner.observed_min_views).all()


def test_the_planner_gains_from_one_channel_and_is_blocked_by_the_other():
    """A predicted wall 6 m ahead of the rover: serving only collision checking, it blocks
    and offers no gain; serving only the gain, it attracts and blocks nothing."""
    from rovergate.types import Channel
    cfg = MissionConfig()
    cfg.scene.bounds_m = BOUNDS
    cfg.scene.d_scene_m = 30.0
    ground, target = flat_ground(), grid_wall(6.0, size=1.5)
    pts = np.vstack([ground, target])
    src = np.r_[np.zeros(len(ground)), np.full(len(target), Source.PREDICTED)].astype(np.uint8)
    views = np.r_[np.full(len(ground), 5), np.zeros(len(target))]  # only the wall is novel
    here = Pose.from_xyz_yaw(0.0, 0.0, 0.0, 0.0)  # facing it
    at_wall = Pose.from_xyz_yaw(6.0, 0.0, 0.0, 0.0)
    seen = {}
    for channel in (Channel.COLLISION, Channel.GAIN):
        channels = np.r_[np.full(len(ground), Channel.BOTH), np.full(len(target), channel)]
        occ = PlannerMap(0, make_cloud(pts, PLANNER_DTYPE, source=src, views=views,
                                       channels=channels.astype(np.uint8)))
        model, _, field = GreedyPlanner(cfg)._setup(0, occ, here)
        seen[channel] = (model.is_free(model.state_of(at_wall)),
                         field.gain(field.visible(model.camera(model.current))))
    assert seen[Channel.COLLISION] == (False, 0)
    free, gain = seen[Channel.GAIN]
    assert free and gain > 0


def test_the_beam_can_route_its_first_motions_around_an_obstacle():
    """A short wall 1.5 m ahead of the rover, novel points beyond it. Straight first motions
    through the wall are rejected; with --planner.route-blocked OMPL reaches some of them,
    so fewer are rejected, and the plan is still a feasible one."""
    import dataclasses
    cfg = MissionConfig()
    cfg.scene.bounds_m = BOUNDS
    cfg.scene.d_scene_m = 30.0
    wall = np.vstack([box_points(1.5, y, 0.0, 0.8) for y in np.arange(-1.0, 1.1, 1.0)])
    ground, target = flat_ground(wall), grid_wall(5.0, size=1.5)
    pts = np.vstack([ground, target])
    src = np.r_[np.zeros(len(ground)), np.full(len(target), Source.PREDICTED)].astype(np.uint8)
    views = np.r_[np.full(len(ground), 5), np.zeros(len(target))]
    occ = PlannerMap(0, make_cloud(pts, PLANNER_DTYPE, source=src, views=views))
    here = Pose.from_xyz_yaw(0.0, 0.0, 0.0, 0.0)
    results = {}
    for route in (False, True):
        c = dataclasses.replace(cfg, planner=dataclasses.replace(
            cfg.planner, name="beam", route_blocked=route))
        results[route] = BeamPlanner(c).plan(0, occ, here)
    straight, routed = results[False], results[True]
    assert routed.reason == "best-feasible"
    assert len(routed.rejected.poses) < len(straight.rejected.poses), (
        len(routed.rejected.poses), len(straight.rejected.poses))


@pytest.mark.parametrize("platform", ["rover", "flyer"])
def test_a_beam_that_discounts_its_look_ahead_to_nothing_is_the_one_level_beam(platform):
    """--planner.beam-discount 0 weighs only the first motion's own gain: the same choice as a
    beam one level deep (same candidates, same order, same OMPL seeds); 1 is the whole gain."""
    import dataclasses
    cfg = MissionConfig()
    cfg.platform = platform
    cfg.scene.bounds_m = BOUNDS
    cfg.scene.d_scene_m = 30.0
    ground = flat_ground(np.zeros((0, 3), np.float32))
    targets = np.vstack([grid_wall(4.0, size=1.5), grid_wall(-4.0, size=1.5)])
    pts = np.vstack([ground, targets])
    src = np.r_[np.zeros(len(ground)), np.full(len(targets), Source.PREDICTED)].astype(np.uint8)
    views = np.r_[np.full(len(ground), 5), np.zeros(len(targets))]
    occ = PlannerMap(0, make_cloud(pts, PLANNER_DTYPE, source=src, views=views))
    here = (Pose.from_xyz_yaw(0.0, 0.0, 0.0, 0.0) if platform == "rover"
            else Pose.from_xyz_yaw_pitch(0.0, 0.0, 1.6, 0.0, 0.0))

    def plan(**kw):
        c = dataclasses.replace(cfg, planner=dataclasses.replace(cfg.planner, name="beam",
                                                                 **kw))
        return BeamPlanner(c).plan(0, occ, here)
    none, one = plan(beam_discount=0.0), plan(beam_depth=1)
    assert none.reason == one.reason == "best-feasible"
    assert none.gain == one.gain > 0
    assert [p.position.tolist() for p in none.path.poses] == [
        p.position.tolist() for p in one.path.poses]
    assert plan(beam_discount=1.0).gain >= none.gain  # the whole look-ahead counts


def test_map_points_inside_the_rover_body_are_not_obstacles():
    """The body occupies the space where it stands (a self filter)."""
    from planner.platforms import outside_body
    T = Pose.from_xyz_yaw(2.0, 1.0, 0.5, np.pi / 2)  # facing +y
    pts = np.array([[2.0, 1.4, 1.0],    # inside: 0.4 m ahead, 0.5 m over the base
                    [2.0, 1.7, 1.0],    # 0.7 m ahead: beyond the 0.5 m half length
                    [2.3, 1.0, 1.0],    # 0.3 m to the right: within the 0.35 m half width
                    [2.0, 1.0, 0.6],    # under the clearance: ground, kept
                    [2.0, 1.0, 1.5]],   # over the body's top: kept
                   dtype=np.float32)
    assert outside_body(pts, T, RoverConfig()).tolist() == [False, True, False, True, True]


def test_ground_comes_from_measurements_where_a_cell_has_them():
    rover = RoverConfig()
    ground = np.array([[x, y, 0.0] for x in np.arange(-2, 2.01, 0.25)
                       for y in np.arange(-2, 2.01, 0.25)], dtype=np.float32)
    low_guess = np.array([[0.1, 0.1, -0.4]], dtype=np.float32)  # a prediction 0.4 m too low
    pts = np.vstack([ground, low_guess])
    predicted = np.r_[np.zeros(len(ground), bool), True]
    blind = OccupancyCollisionModel(pts, rover, BOUNDS, 0.5, 0.15, 0.0)
    told = OccupancyCollisionModel(pts, rover, BOUNDS, 0.5, 0.15, 0.0, predicted=predicted)
    assert blind.ground_z(0.1, 0.1) == pytest.approx(-0.4)
    assert told.ground_z(0.1, 0.1) == pytest.approx(0.0)


def test_beam_segments_are_checked_along_their_length():
    """A straight segment through a wall is blocked though both of its ends are free."""
    from planner.platforms import motion_model
    cfg = MissionConfig(platform="flyer")
    cfg.scene.bounds_m = BOUNDS
    cfg.scene.d_scene_m = 30.0
    wall = np.array([[3.0, y, z] for y in np.arange(-3, 3.01, 0.1)
                     for z in np.arange(0.0, 5.01, 0.1)])
    pts = np.vstack([flat_ground(), wall]).astype(np.float32)
    model = motion_model(cfg, pts, Pose.from_xyz_yaw_pitch(0.0, 0.0, 1.6, 0.0, 0.0))
    here, behind, beside = model.current, (5.0, 0.0, 1.6, 0.0, 0.0), (0.0, 2.0, 1.6, 0.0, 0.0)
    assert model.is_free(behind) and model.is_free(beside)
    assert not model.segment_free(here, behind)
    assert model.segment_free(here, beside)


def test_gain_field_views_are_visible_mask_to_the_bit():
    """GainField.visible projects only the primitives of the blocks in a view's frustum, and
    each as visible_mask does: the same primitives come out, for views from anywhere, in any
    direction, over terrain, walls and scattered points."""
    from scipy.spatial.transform import Rotation

    from planner.gain import _erode
    rng = np.random.default_rng(7)
    xs, ys = np.meshgrid(np.arange(-15, 15, 0.15), np.arange(-15, 15, 0.15))
    terrain = np.c_[xs.ravel(), ys.ravel(), np.sin(xs.ravel() / 3) + 0.1 * ys.ravel()]
    pts = np.vstack([terrain, grid_wall(4.0, n=60, size=3.0), grid_wall(-9.0, n=40),
                     rng.uniform([-16, -16, -2], [16, 16, 6], (3000, 3))]).astype(np.float32)
    novel = rng.random(len(pts)) < 0.5
    field = GainField(pts, novel, 0.3, K, 0.3, 20.0, 0.3)
    assert field.weight.sum() == novel.sum()
    rotations = Rotation.random(60, random_state=3).as_matrix()
    seen_any = 0
    cameras, expect = [], []
    for i, R in enumerate(rotations):
        T = np.eye(4)
        T[:3, :3] = R if i % 2 else R_BODY_OPTICAL @ Rotation.from_euler(
            "y", rng.uniform(-0.6, 0.2)).as_matrix()  # half of them level-ish, as a camera
        T[:3, 3] = rng.uniform([-20, -20, -1], [20, 20, 6])
        expected = np.flatnonzero(visible_mask(field.centres, T, K, 0.3, 20.0, 0.3))
        assert np.array_equal(field.visible(T), expected)
        seen_any += len(expected) > 50
        cameras.append(T)
        expect.append(expected)
    assert seen_any > 10  # the views did see things
    together = field.visible_many(cameras)  # every view with its own z-buffer
    assert all(np.array_equal(a, b) for a, b in zip(together, expect, strict=True))
    # The z-buffer's erosion is scipy's 3 x 3 minimum filter with edges repeated.
    from scipy.ndimage import minimum_filter
    for shape in [(30, 40), (1, 1), (1, 5), (5, 1), (7, 3)]:
        z = rng.random(shape)
        z[rng.random(shape) < 0.5] = np.inf
        assert np.array_equal(_erode(z), minimum_filter(z, size=3, mode="nearest"))


def test_the_rover_grounds_box_minimum_is_scipys_minimum_filter():
    """The collision model's ground (the lowest point under the rover's footprint) is
    scipy's minimum filter with edges repeated, to the bit, at every box size it uses."""
    from scipy.ndimage import minimum_filter

    from planner.collision import _box_minimum
    rng = np.random.default_rng(3)
    for shape, size in [((60, 45), 9), ((30, 40), 3), ((1, 1), 5), ((2, 7), 11), ((9, 1), 7)]:
        z = rng.normal(size=shape)
        z[rng.random(shape) < 0.4] = np.inf
        assert np.array_equal(_box_minimum(z, size), minimum_filter(z, size=size, mode="nearest"))


def test_collision_boxes_are_reused_not_made_anew_each_step():
    """python-fcl never frees a CollisionObject: the models of successive steps take their
    boxes from one pool and give them back, so a mission makes only as many as one step
    holds, and each model answers as one built from fresh boxes would."""
    import gc

    from planner.collision import box_pool
    rng = np.random.default_rng(3)
    pool = box_pool(0.15)
    poses = [(float(x), float(y), float(a)) for x, y, a in rng.uniform(-6, 6, (40, 3))]
    first = None
    for step in range(12):
        rocks = np.vstack([box_points(*rng.uniform(-6, 6, 2), 0.0, 0.6) for _ in range(6)])
        m = model(flat_ground(rocks))
        answers = [m.is_free(*p) for p in poses]
        if step == 2:
            first = pool.made
        # Built now from its own points, the answers are the same.
        again = model(flat_ground(rocks))
        assert [again.is_free(*p) for p in poses] == answers
        assert any(answers) and not all(answers)
        del m, again
        gc.collect()
    # After the first few steps (the pool's high-water mark), nothing more is made.
    assert pool.made <= first * 1.5, (first, pool.made)


def _rolling_site(half_m, seed=3, spacing=0.4):
    """A synthetic map over a square of half-side ``half_m``: rolling ground sampled every
    ``spacing`` metres and rock-like blocks standing on it."""
    rng = np.random.default_rng(seed)
    g = np.arange(-half_m, half_m, spacing)
    X, Y = np.meshgrid(g, g)
    Z = 0.8 * np.sin(X / 7.0) * np.cos(Y / 9.0)
    pts = [np.c_[X.ravel(), Y.ravel(), Z.ravel()]]
    for cx, cy in rng.uniform(-half_m + 2, half_m - 2, (int(half_m * half_m / 40), 2)):
        z0 = 0.8 * np.sin(cx / 7.0) * np.cos(cy / 9.0)
        pts.append(box_points(cx, cy, z0, z0 + rng.uniform(0.2, 1.2), half=0.3))
    return np.vstack(pts).astype(np.float32)


def _site_map(pts, seed=4):
    rng = np.random.default_rng(seed)
    return PlannerMap(0, make_cloud(pts, PLANNER_DTYPE, views=rng.integers(0, 4, len(pts))))


def test_the_local_window_sees_what_the_whole_map_shows_near_the_vehicle():
    # A 200 m map: the planner reads the 100 m square around the rover. Every view a step can
    # take (within the beam's reach) renders the same gain, and every state it may plan
    # through is judged the same, as on the whole map.
    from planner.planner import gain_field
    from planner.platforms import motion_model
    from rovergate.geometry import camera_from_base
    cfg = MissionConfig()
    cfg.scene.bounds_m = (-100.0, -100.0, -2.0, 100.0, 100.0, 3.0)
    occ = _site_map(_rolling_site(100.0))
    here = Pose.from_xyz_yaw(31.3, -17.9, 0.0, 0.4)
    local, kept = occ.within(31.3, -17.9, cfg.planner.local_half_m)
    assert kept is not None and 0.2 < len(kept) / len(occ.points) < 0.3
    whole_field = gain_field(cfg, np.c_[occ.points["x"], occ.points["y"], occ.points["z"]],
                             novel_mask(occ, 2))
    pts = np.c_[local.points["x"], local.points["y"], local.points["z"]]
    field = gain_field(cfg, pts, novel_mask(local, 2))
    rng = np.random.default_rng(0)
    reach = cfg.planner.beam_depth * cfg.planner.max_step_m
    for x, y, yaw in np.c_[rng.uniform(-reach, reach, (40, 2)) + [31.3, -17.9],
                           rng.uniform(-np.pi, np.pi, 40)]:
        camera = camera_from_base(Pose.from_xyz_yaw(x, y, 0.0, yaw).matrix(), cfg.sensor,
                                  cfg.platform)
        assert field.gain(field.visible(camera)) == whole_field.gain(whole_field.visible(camera))
    big = MissionConfig()
    big.scene.bounds_m = cfg.scene.bounds_m
    big.planner.local_half_m = 1000.0  # the whole map
    near = motion_model(cfg, pts, here)
    whole = motion_model(big, np.c_[occ.points["x"], occ.points["y"], occ.points["z"]], here)
    box = near.inner_box()
    assert box[2] - box[0] == pytest.approx(2 * (cfg.planner.local_half_m - 10.0))
    states = np.c_[rng.uniform(box[0], box[2], 300), rng.uniform(box[1], box[3], 300),
                   rng.uniform(-np.pi, np.pi, 300)]
    free = [near.is_free(tuple(s)) for s in states]
    assert free == [whole.is_free(tuple(s)) for s in states]
    assert 0 < sum(free) < len(free)  # both kinds of state were judged


@pytest.mark.parametrize("planner", [GreedyPlanner, BeamPlanner])
def test_a_box_of_interest_40_m_across_is_planned_on_its_whole_map(planner):
    # The default window covers such a box from anywhere in it: a rover at its corner, with
    # the map reaching 15 m beyond the box as a camera sees, plans as with no window at all.
    pts = _rolling_site(35.0, seed=8)
    outcomes = []
    for half in (50.0, 1000.0):
        cfg = MissionConfig()
        cfg.scene.bounds_m = (-20.0, -20.0, -2.0, 20.0, 20.0, 3.0)
        cfg.planner.local_half_m = half
        result = planner(cfg).plan(3, _site_map(pts), Pose.from_xyz_yaw(19.0, 18.5, 0.0, 2.5))
        outcomes.append([(p.position.tolist(), p.yaw) for p in result.path.poses])
    assert outcomes[0] == outcomes[1]
