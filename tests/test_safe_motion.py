"""Motion that never goes unchecked, and each step judged against truth (built cases)."""

from __future__ import annotations

import numpy as np
import pytest

from mission.scoring.evaluation import (
    PLANNER_FAULT,
    UNSEEN,
    StepEvaluator,
    collision_class,
    stuck_flags,
)
from planner.freespace import FreeSpace
from planner.platforms import FlyerModel, RoverModel
from rovergate.config import MissionConfig
from rovergate.geometry import R_BODY_OPTICAL
from rovergate.types import (
    PLANNER_DTYPE,
    CameraIntrinsics,
    ExecutionReport,
    PlannerMap,
    PlanPath,
    Pose,
    Source,
    make_cloud,
)

BOUNDS = (-10.0, -10.0, -1.0, 10.0, 10.0, 5.0)
K = CameraIntrinsics.from_fov(64, 48, 45.0)


def mission(platform: str) -> MissionConfig:
    cfg = MissionConfig()
    cfg.platform = platform
    cfg.scene.bounds_m = BOUNDS
    cfg.scene.d_scene_m = 30.0
    return cfg


def ground(slope_deg: float = 0.0, spacing: float = 0.15) -> np.ndarray:
    xs, ys = np.meshgrid(np.arange(-9.5, 9.5, spacing), np.arange(-9.5, 9.5, spacing))
    z = np.tan(np.radians(slope_deg)) * xs
    return np.c_[xs.ravel(), ys.ravel(), z.ravel()].astype(np.float32)


def planner_map(points: np.ndarray, source: int = Source.OBSERVED, views: int = 5) -> PlannerMap:
    return PlannerMap(0, make_cloud(points, PLANNER_DTYPE, source=source, views=views))


# --- collision classes and stuck ------------------------------------------------------------

def test_a_collision_with_geometry_the_map_held_is_a_planner_fault():
    hit = ExecutionReport(3, True, 1, -1.0, 0.4, 0.2, contact=(2.0, 0.0, 0.5))
    rock = np.array([[2.05, 0.0, 0.5], [2.05, 0.1, 0.6]], dtype=np.float32)
    elsewhere = np.array([[5.0, 5.0, 0.5]], dtype=np.float32)
    here = Pose.from_xyz_yaw(0.0, 0.0, 0.0, 0.0)
    for platform in ("flyer", "rover"):
        cfg = mission(platform)
        floor = ground()
        held = planner_map(np.vstack([floor, rock]))
        assert collision_class(hit, held, cfg, here) == PLANNER_FAULT, platform
        assert collision_class(hit, planner_map(np.vstack([floor, elsewhere])), cfg,
                               here) == UNSEEN, platform
        clear = ExecutionReport(3, False, 0, 0.4, 2.0, 1.0)
        assert collision_class(clear, held, cfg, here) is None
    # The rover hit a rock where the map showed only ground: the map did not hold it.
    low = ExecutionReport(3, True, 1, -1.0, 0.4, 0.2, contact=(2.0, 0.0, 0.1))
    assert collision_class(low, planner_map(ground()), mission("rover"), here) == UNSEEN


def test_stuck_is_no_net_progress_over_the_window():
    moving = np.c_[np.arange(30) * 1.0, np.zeros(30), np.zeros(30)]
    dithering = np.c_[np.tile([0.0, 0.3], 15), np.zeros(30), np.zeros(30)]
    assert not stuck_flags(moving).any()
    flags = stuck_flags(dithering, window=10, min_m=0.5)
    assert not flags[:10].any() and flags[10:].all()


# --- every motion checked -------------------------------------------------------------------

def test_the_rover_leaves_a_slope_it_stands_on_and_still_sees_a_rock_there():
    cfg = mission("rover")
    slope = ground(slope_deg=15.0)
    here = Pose.from_xyz_yaw(0.0, 0.0, 0.0, 0.0)
    model = RoverModel(cfg, slope, here)
    assert model.is_free(model.current)           # the slope is ground, not an obstacle
    assert model.is_free((2.0, 0.0, 0.0))
    rz = np.tan(np.radians(15.0)) * 2.0
    rock = np.array([[2.0 + dx, dy, rz + h] for dx in (-0.1, 0.0, 0.1) for dy in (-0.1, 0, 0.1)
                     for h in (0.3, 0.45, 0.6)], dtype=np.float32)
    blocked = RoverModel(cfg, np.vstack([slope, rock]), here)
    assert not blocked.is_free((2.0, 0.0, 0.0))   # a rock standing 0.3-0.6 m out of the slope


def test_a_flyer_the_map_now_blocks_leaves_only_by_a_checked_escape():
    cfg = mission("flyer")
    point = np.array([0.0, 0.35, 1.6])  # 0.35 m to its left: inside its reach (0.4 m)
    pts = np.vstack([ground(), point]).astype(np.float32)
    model = FlyerModel(cfg, pts, Pose.from_xyz_yaw_pitch(0.0, 0.0, 1.6, 0.0, 0.0))
    start = model.current
    assert not model.is_free(start)
    # Without the escape, every state after the start is judged: no motion leaves.
    assert model.plan(start, (0.0, -2.0, 1.6, 0.0, 0.0), seed=1) is None
    model.leave_blocked_start()
    assert model.prefix == [start] and model.is_free(model.current)
    away = np.asarray(model.current[:3]) - np.asarray(start[:3])
    assert away[1] < 0 and np.linalg.norm(away) <= 0.6  # straight away from the point
    path = model.plan(model.current, (0.0, -2.0, 1.6, 0.0, 0.0), seed=1)
    assert path is not None and all(model.is_free(s) for s in path)


def test_a_flyer_escape_may_pass_nearer_than_a_check_before_never_nearer_than_its_start():
    # A point 0.35 m to its left blocks it; a second, ahead and to the right, lies along the
    # way out: the distance to the map grows, shrinks while the way passes the second point
    # (never under where it started), then grows again. The rule is the start's distance,
    # not the last check's (issue 14's note): the escape gets out.
    cfg = mission("flyer")
    pts = np.vstack([ground(), [[0.0, 0.35, 1.6], [0.4, -0.25, 1.6]]]).astype(np.float32)
    model = FlyerModel(cfg, pts, Pose.from_xyz_yaw_pitch(0.0, 0.0, 1.6, 0.0, 0.0))
    start = model.sphere.distance(np.array([0.0, 0.0, 1.6]))
    end = model.escape()
    assert end is not None and model.is_free(end)
    assert end[:3] == pytest.approx((0.0, -0.55, 1.6))
    way = [model.sphere.distance(np.array([0.0, -d, 1.6])) for d in np.arange(0.05, 0.56, 0.05)]
    assert min(way) >= start - 1e-9
    assert any(b < a for a, b in zip(way, way[1:], strict=False))  # it did shrink on the way


def test_a_flyer_above_its_altitude_band_descends_back_into_it():
    # The flyer got to 7 m over a ground the map then placed lower (a prediction filled the
    # floor below it): nothing is near it, but it is above the band (6 m over the ground).
    # Before the return every motion's first states were out of the band: it only turned.
    cfg = mission("flyer")
    model = FlyerModel(cfg, ground(), Pose.from_xyz_yaw_pitch(0.0, 0.0, 7.0, 0.0, 0.0))
    start = model.current
    assert not model.is_free(start) and model.sphere.is_free(*start[:3], band=False)
    assert not model.segment_free(start, (2.0, 0.0, 5.0, 0.0, 0.0))
    model.leave_blocked_start()
    assert model.prefix == [start] and model.is_free(model.current)
    assert model.current[:2] == start[:2] and 5.5 < model.current[2] < 6.0
    assert model.segment_free(model.current, (2.0, 0.0, 5.0, 0.0, 0.0))
    # A map point below it, within the margin of the way down: it may not descend past it.
    pts = np.vstack([ground(), [[0.0, 0.3, 6.5]]]).astype(np.float32)
    blocked = FlyerModel(cfg, pts, Pose.from_xyz_yaw_pitch(0.0, 0.0, 7.0, 0.0, 0.0))
    blocked.leave_blocked_start()
    assert blocked.prefix == [] and blocked.current == start
    # Nor through space no camera ray has shown free.
    free = FreeSpace((-10, -10, -1, 10, 10, 12), 0.25, 0.3, 20.0)
    free.add_body(np.array([0.0, 0.0, 7.0]), 0.3)
    unknown = FlyerModel(cfg, ground(), Pose.from_xyz_yaw_pitch(0.0, 0.0, 7.0, 0.0, 0.0),
                         free=free)
    unknown.leave_blocked_start()
    assert unknown.prefix == []
    # A drop deeper than one step's budget (3 m) is made up over several steps.
    high = FlyerModel(cfg, ground(), Pose.from_xyz_yaw_pitch(0.0, 0.0, 11.0, 0.0, 0.0))
    high.leave_blocked_start()
    assert high.prefix and high.current[2] == pytest.approx(8.0)


def test_a_rover_the_map_now_blocks_backs_out_with_its_true_body():
    cfg = mission("rover")
    # A rock just inside the checked body's margin ahead of the rover, clear of the body.
    rock = np.array([[0.65, dy, 0.5] for dy in (-0.1, 0.0, 0.1)], dtype=np.float32)
    model = RoverModel(cfg, np.vstack([ground(), rock]), Pose.from_xyz_yaw(0.0, 0.0, 0.0, 0.0))
    start = model.current
    assert not model.is_free(start) and model.ground.is_free(*start, margin=False)
    model.leave_blocked_start()
    assert model.prefix == [start] and model.is_free(model.current)
    assert model.current[0] < 0  # it backed away from the rock


def test_a_rover_stopped_against_a_rock_along_its_side_moves_away_from_it():
    cfg = mission("rover")
    # A rock wall along the rover's right side, 6 cm out from it (half-width 0.35 m), as the
    # bumper leaves it; its samples run the body's length and beyond, so straight ahead and
    # straight back both keep the true body within a voxel of it, and a turn in place swings
    # an end into it. With only those escapes the rover stayed where it was for the rest of
    # the mission (canyon/a, beam planner).
    wall = np.array([[x, -0.41 - dy, z] for x in np.arange(-1.0, 1.01, 0.1)
                     for dy in (0.0, 0.1) for z in (0.4, 0.6)], dtype=np.float32)
    here = Pose.from_xyz_yaw(0.0, 0.0, 0.0, 0.0)
    model = RoverModel(cfg, np.vstack([ground(), wall]), here)
    start = model.current
    assert not model.is_free(start)
    assert not model.ground.is_free(0.05, 0.0, 0.0, margin=False)  # nor can it creep along
    model.leave_blocked_start()
    assert model.prefix and model.prefix[0] == start and model.is_free(model.current)
    # Sideways, away from the wall, heading kept: the shortest way out.
    assert model.current[1] > 0 and model.current[2] == 0.0
    assert model.current[1] == pytest.approx(0.15) and abs(model.current[0]) < 1e-9
    # Every state of the way: the narrowed true body off the wall, the turn checked too.
    way = [*model.prefix, model.current]
    assert all(model.ground.is_free(*s, margin="escape") for s in way[1:])
    assert np.hypot(*np.subtract(model.current[:2], start[:2])) <= 0.6 + 1e-9
    # No way out at all (walled in on both sides, and ahead and behind): it stays.
    box = np.vstack([wall, wall * [1, -1, 1],
                     [[x, y, z] for x in (-0.62, 0.62) for y in np.arange(-0.4, 0.41, 0.1)
                      for z in (0.4, 0.6)]]).astype(np.float32)
    trapped = RoverModel(cfg, np.vstack([ground(), box]), here)
    trapped.leave_blocked_start()
    assert trapped.prefix == [] and trapped.current == start


def test_a_rover_touching_the_scene_where_it_stands_escapes_away_from_the_contact():
    """The bumper touched the scene at the rover's rear right corner where it now stands
    (arch_field/a, seed 1: before, the self filter dropped that contact as a point inside the
    body, and the rover drove into it again seven steps running)."""
    cfg = mission("rover")
    here = Pose.from_xyz_yaw(0.0, 0.0, 0.0, 0.0)
    contact = np.array([[-0.51, -0.36, 0.6]], dtype=np.float32)
    model = RoverModel(cfg, ground(), here, contacts=contact)
    start = model.current
    assert len(model.contacts) == 1 and not model.is_free(start)
    # Backing up, or moving right, comes nearer.
    gap = model._contact_gap(start, model.contacts[:, :2])
    assert model._contact_gap((-0.05, 0.0, 0.0), model.contacts[:, :2]) < gap
    assert model._contact_gap((0.0, -0.05, 0.0), model.contacts[:, :2]) < gap
    model.leave_blocked_start()
    assert model.prefix and model.is_free(model.current)
    way = [*model.prefix, model.current]
    gaps = [model._contact_gap(s, model.contacts[:, :2]) for s in way]
    assert all(b >= gaps[0] for b in gaps[1:]) and gaps[-1] >= 0.1
    assert model.current[0] > 0 or model.current[1] > 0  # away: ahead or to the left


def test_the_flyer_keeps_to_known_free_space():
    cfg = mission("flyer")
    free = FreeSpace((-10, -10, -1, 10, 10, 6), 0.25, 0.3, 20.0)
    T = np.eye(4)
    T[:3, :3] = R_BODY_OPTICAL  # looking along +x from (0, 0, 1.6)
    T[:3, 3] = [0.0, 0.0, 1.6]
    wall = np.full((K.height, K.width), 5.0, dtype=np.float32)
    free.add_frame(T, K, wall)
    free.add_body(np.array([0.0, 0.0, 1.6]), 0.3)
    assert free.is_free(2.0, 0.0, 1.6) and not free.is_free(6.0, 0.0, 1.6)
    assert not free.is_free(-2.0, 0.0, 1.6)          # behind the camera: never seen
    assert free.is_free(0.0, 0.0, 1.6)               # where the flyer is
    dropped = FreeSpace((-10, -10, -1, 10, 10, 6), 0.25, 0.3, 20.0)
    dropped.add_frame(T, K, np.full_like(wall, np.nan))   # invalid returns: no evidence
    assert not dropped.free.any()
    nothing = FreeSpace((-10, -10, -1, 10, 10, 6), 0.25, 0.3, 20.0)
    nothing.add_frame(T, K, np.full_like(wall, np.inf))   # nothing within range: carve it
    assert nothing.is_free(3.0, 0.0, 1.6) and nothing.free.sum() > 2 * free.free.sum()
    model = FlyerModel(cfg, ground(), Pose.from_xyz_yaw_pitch(0.0, 0.0, 1.6, 0.0, 0.0), free=free)
    assert model.plan(model.current, (2.0, 0.0, 1.6, 0.0, 0.0), seed=1) is not None
    assert model.plan(model.current, (-2.0, 0.0, 1.6, 0.0, 0.0), seed=1) is None


def test_a_rover_turn_is_checked_along_its_sweep():
    cfg = mission("rover")
    # A rock off the rover's front-left corner: the rover at yaw 0 and at yaw 90 degrees
    # clears it, the body in between sweeps through it.
    rock = np.array([[0.58 + dx, 0.58 + dy, 0.5] for dx in (-0.02, 0.02) for dy in (-0.02, 0.02)],
                    dtype=np.float32)
    model = RoverModel(cfg, np.vstack([ground(), rock]), Pose.from_xyz_yaw(0.0, 0.0, 0.0, 0.0))
    turned = (0.0, 0.0, np.pi / 2)
    assert model.is_free(model.current) and model.is_free(turned)
    assert not model.is_free_turn(turned)


# --- the paper's decision-level measure -----------------------------------------------------

def test_gain_share_and_rejections_from_oracle_false_positives():
    cfg = mission("flyer")
    floor = ground(spacing=0.3)
    evaluator = StepEvaluator(cfg, floor)              # the truth: the floor alone
    ahead = np.array([[6.0, y, z] for y in np.linspace(-1, 1, 5) for z in np.linspace(1.5, 3.5, 5)],
                     dtype=np.float32)  # a predicted wall, all farther than delta from the truth
    blocker = np.array([[2.0, 0.0, 1.6]], dtype=np.float32)  # a false positive on the goal
    pts = np.vstack([floor, ahead, blocker])
    source = np.r_[np.full(len(floor), Source.OBSERVED), np.full(len(ahead) + 1,
                                                                 Source.PREDICTED)]
    views = np.r_[np.full(len(floor), 5), np.zeros(len(ahead) + 1)]  # the floor is seen
    pm = PlannerMap(0, make_cloud(pts, PLANNER_DTYPE, source=source, views=views))
    here = Pose.from_xyz_yaw_pitch(0.0, 0.0, 1.6, 0.0, 0.0)
    goal = Pose.from_xyz_yaw_pitch(1.0, 0.0, 1.6, 0.0, 0.0)
    rejected = PlanPath(0, [Pose.from_xyz_yaw_pitch(2.0, 0.0, 1.6, 0.0, 0.0)])
    d = evaluator.decision(pm, PlanPath(0, [here, goal]), rejected, here)
    assert d.fp_gain_share == 1.0   # all it would see new is the false wall
    assert d.rejected_by_fp == 1    # the goal the false point blocked is free without it
    truth_only = planner_map(floor)
    d = evaluator.decision(truth_only, PlanPath(0, [here, goal]), PlanPath(0, []), here)
    assert d.fp_gain_share == 0.0 and d.rejected_by_fp == 0

