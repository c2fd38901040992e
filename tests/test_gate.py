"""The observation-gated filter (equation 4) and the conditions of equation 2, on built cases."""

from __future__ import annotations

import numpy as np
import pytest

from gate.filter import ObservationGate
from gate.gate import Gate, oracle_tags
from gate.views import pixels
from rovergate.conditions import CONDITIONS
from rovergate.config import GateConfig, SensorConfig
from rovergate.geometry import R_BODY_OPTICAL
from rovergate.types import (
    PREDICTED_DTYPE,
    SURFACE_DTYPE,
    CameraIntrinsics,
    Channel,
    MapperOutput,
    Pose,
    Source,
    make_cloud,
    xyz,
)

K = CameraIntrinsics.from_fov(64, 48, 45.0)


def camera_looking_along_x(x: float = 0.0) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R_BODY_OPTICAL
    T[:3, 3] = [x, 0.0, 1.0]
    return T


TARGET = np.array([[10.0, 0.0, 1.0]], dtype=np.float32)   # straight ahead, in range
BEHIND = np.array([[-10.0, 0.0, 1.0]], dtype=np.float32)  # never in the frustum


def make_gate(k=2, eps=0.5):
    return ObservationGate(k=k, epsilon_m=eps, min_range_m=0.3, max_range_m=20.0)


def test_counts_frustum_inclusions():
    g = make_gate()
    for _ in range(3):
        g.add_frustum(camera_looking_along_x(), K)
    assert g.exposure_counts(np.vstack([TARGET, BEHIND])).tolist() == [3, 0]


def test_the_gate_counts_a_frame_where_the_views_and_the_gain_see_a_pixel():
    # One projection (rovergate.geometry.project): a point counts toward n_t exactly when
    # pixels_of puts it on a pixel, edges and ranges included, over frames of two cameras.
    from rovergate.geometry import pixels_of
    rng = np.random.default_rng(3)
    g, expected = make_gate(), 0
    points = rng.uniform([-2.0, -12.0, -8.0], [24.0, 12.0, 10.0], (4000, 3))
    cams = [(camera_looking_along_x(x), k) for x in (0.0, 1.5, 3.0)
            for k in (K, CameraIntrinsics.from_fov(31, 17, 70.0))]
    for T, k in cams:
        g.add_frustum(T, k)
        R = T[:3, :3].T
        idx = pixels_of(points @ R.T - R @ T[:3, 3], k, 0.3, 20.0)[0]
        hit = np.zeros(len(points), dtype=np.int32)
        hit[idx] = 1
        expected = expected + hit
    assert g.exposure_counts(points).tolist() == expected.tolist()
    assert 0 < (expected > 0).mean() < 1  # some in view, some not: the test can fail


def test_out_of_range_is_not_exposed():
    g = make_gate()
    g.add_frustum(camera_looking_along_x(), K)
    far = np.array([[25.0, 0.0, 1.0]], dtype=np.float32)
    assert g.exposure_counts(far).tolist() == [0]


def test_kept_below_k_suppressed_at_k_without_support():
    g = make_gate(k=2)
    no_surface = np.zeros((0, 3), dtype=np.float32)
    g.add_frustum(camera_looking_along_x(), K)
    assert not g.unsupported(TARGET, no_surface)[0]          # n=1 < K: kept
    g.add_frustum(camera_looking_along_x(1.0), K)
    assert g.unsupported(TARGET, no_surface)[0]              # n=2 = K, no support: suppressed


def test_support_within_epsilon_keeps_a_point():
    g = make_gate(k=2, eps=0.5)
    for x in (0.0, 1.0, 2.0):
        g.add_frustum(camera_looking_along_x(x), K)
    near = TARGET + np.array([0.4, 0, 0], dtype=np.float32)
    far = TARGET + np.array([0.6, 0, 0], dtype=np.float32)
    assert not g.unsupported(TARGET, near)[0]
    assert g.unsupported(TARGET, far)[0]


def test_later_support_restores_a_suppressed_point():
    g = make_gate(k=2, eps=0.5)
    g.add_frustum(camera_looking_along_x(), K)
    g.add_frustum(camera_looking_along_x(), K)
    assert g.unsupported(TARGET, np.zeros((0, 3), np.float32))[0]
    surface_later = TARGET + np.array([0.0, 0.2, 0.0], dtype=np.float32)
    assert not g.unsupported(TARGET, surface_later)[0]


BOUNDS = (-20.0, -20.0, -5.0, 20.0, 20.0, 10.0)
FAR = np.full((K.height, K.width), 30.0, dtype=np.float32)  # every ray ends beyond 20 m


def new_gate(name, reference=None, bounds=BOUNDS):
    return Gate(name, GateConfig(), SensorConfig(), 10.0, bounds, 0.3, reference)


def _mapped(surface_xyz, pred_xyz):
    return MapperOutput(3, make_cloud(surface_xyz, SURFACE_DTYPE, views=1),
                        make_cloud(pred_xyz, PREDICTED_DTYPE, probability=0.9))


def test_gated_condition_drops_unsupported_points_only():
    gate = new_gate("gated")  # epsilon 0.3 m
    surface = np.array([[10.0, 0.0, 1.2]], dtype=np.float32)
    pred = np.vstack([TARGET, TARGET + [[0, 3.0, 0]], BEHIND]).astype(np.float32)
    pose = Pose.from_matrix(camera_looking_along_x())
    gate.step(_mapped(surface, pred), pose, K, FAR)
    out = gate.step(_mapped(surface, pred), pose, K, FAR)
    src = out.points["source"]
    kept = out.points[src == Source.PREDICTED]
    # Supported (near the surface) and never-seen (behind) predictions stay; the exposed,
    # unsupported one is suppressed.
    assert out.suppressed == 1
    assert sorted(kept["x"].tolist()) == [-10.0, 10.0]
    assert (src == Source.OBSERVED).sum() == 1


@pytest.mark.parametrize("name", sorted(CONDITIONS))
def test_every_condition_composes_as_equation_2(name):
    ref = np.array([[0, 0, 0], [5, 5, 0], [9, 9, 9]], dtype=np.float32)
    surface = np.array([[0, 0, 0.05]], dtype=np.float32)
    pred = np.array([[5, 5, 0.1], [3, 3, 3]], dtype=np.float32)  # one true, one false positive
    gate = new_gate(name, ref)
    out = gate.step(_mapped(surface, pred), Pose.from_matrix(camera_looking_along_x()), K, FAR)
    counts = {s: int((out.points["source"] == s).sum()) for s in range(4)}
    expected = {
        "obs": {0: 1, 1: 0, 2: 0, 3: 0},
        "learned": {0: 1, 1: 2, 2: 0, 3: 0},
        "learned-fp": {0: 1, 1: 1, 2: 0, 3: 0},
        "learned+fn": {0: 1, 1: 2, 2: 2, 3: 0},   # (0,0,0) and (9,9,9) have no prediction near
        "truth": {0: 0, 1: 0, 2: 0, 3: 3},
        "gated": {0: 1, 1: 2, 2: 0, 3: 0},        # one frustum only: nothing suppressed yet
        "gated-ray": {0: 1, 1: 2, 2: 0, 3: 0},    # likewise
        "gated-ray-inf": {0: 1, 1: 2, 2: 0, 3: 0},  # likewise
        "gated-pose": {0: 1, 1: 2, 2: 0, 3: 0},   # likewise
        "gated-split": {0: 1, 1: 2, 2: 0, 3: 0},  # likewise
    }[name]
    assert counts == expected


def test_every_condition_with_a_prediction_has_its_variant_and_no_other_does():
    # A gate variant is one entry of gate.gate.VARIANTS beside its condition; the gate asks
    # the entry (its filter, what it keeps) rather than branching on the name.
    from gate.filter import PoseGate, RayGate, SplitGate
    from gate.gate import VARIANTS
    assert set(VARIANTS) == {n for n, c in CONDITIONS.items() if c.needs_prediction}
    filters = {n: type(new_gate(n, np.zeros((1, 3), np.float32)).filter) for n in CONDITIONS}
    assert (filters["gated-ray"], filters["gated-pose"], filters["gated-split"]) == \
        (RayGate, PoseGate, SplitGate)
    assert filters["gated-ray-inf"] is RayGate
    assert new_gate("gated-ray-inf", np.zeros((1, 3), np.float32)).filter.beyond_range_passes
    assert not new_gate("gated-ray", np.zeros((1, 3), np.float32)).filter.beyond_range_passes
    # gated-ray-inf has its own K and epsilon (the sweep's choice), the others the gate's.
    from rovergate.config import GateConfig
    inf, frustum = (new_gate(n, np.zeros((1, 3), np.float32)).filter
                    for n in ("gated-ray-inf", "gated"))
    cfg = GateConfig()
    assert (inf.k, frustum.k) == (cfg.ray_inf_k, cfg.k)
    assert inf.epsilon_m == pytest.approx(frustum.epsilon_m * cfg.ray_inf_epsilon_frac
                                          / cfg.epsilon_frac)
    assert {filters[n] for n in CONDITIONS if not n.startswith("gated-")} == {ObservationGate}


def test_oracle_tags_follow_the_paper():
    ref = np.array([[0, 0, 0], [1, 0, 0]], dtype=np.float32)
    pred = np.array([[0.05, 0, 0], [5, 0, 0]], dtype=np.float32)
    tags = oracle_tags(pred, ref, delta_m=0.1)
    assert tags.false_positive.tolist() == [False, True]
    assert tags.false_negative_points.tolist() == [[1.0, 0.0, 0.0]]


def test_unsupported_equals_equation_4_computed_directly():
    """The filter's shortcuts (supported points skip the count; counts stop at K) change
    nothing: U_t is equation 4 evaluated on every point and every frustum."""
    rng = np.random.default_rng(3)
    g = make_gate(k=2, eps=0.8)
    for yaw in rng.uniform(-0.6, 0.6, 40):  # more frustums than one chunk of the count
        T = camera_looking_along_x()
        c, s = np.cos(yaw), np.sin(yaw)
        T[:3, :3] = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]) @ T[:3, :3]
        g.add_frustum(T, K)
    pts = rng.uniform([-2, -8, -3], [15, 8, 3], (3000, 3))
    surface = rng.uniform([-2, -8, -3], [15, 8, 3], (500, 3))
    counts = g.exposure_counts(pts)
    d = np.min(np.linalg.norm(pts[:, None] - surface[None], axis=2), axis=1)
    expected = (counts >= 2) & (d > 0.8)
    assert 0 < expected.sum() < len(pts)
    assert np.array_equal(g.unsupported(pts, surface), expected)
    assert np.array_equal(np.minimum(g.exposure_counts(pts, stop_at=2), 2), np.minimum(counts, 2))


def test_one_rule_of_views_for_every_source():
    """Every point the planner receives carries the frames that saw its place: truth and
    predicted points as observed ones, with no borrowing from the reconstruction."""
    ref = np.array([[10, 0, 1], [-10, 0, 1]], dtype=np.float32)  # ahead; behind the camera
    pose = Pose.from_matrix(camera_looking_along_x())
    for name in ("truth", "learned"):
        gate = new_gate(name, ref)
        for _ in range(3):
            out = gate.step(_mapped(ref[:1], ref), pose, K, FAR)
        assert out.points["views"].tolist() == ([3, 0] if name == "truth" else [3, 3, 0])


def test_an_occluded_point_or_a_dropped_return_is_not_a_view():
    from gate.views import ViewCounter
    views = ViewCounter(0.3, 20.0, tolerance_m=0.3)
    T = camera_looking_along_x()
    wall = np.full((K.height, K.width), 5.0, dtype=np.float32)   # a wall 5 m ahead
    views.add_frame(T, K, wall)
    dropped = FAR.copy()
    dropped[:, :] = np.nan                                       # no return anywhere
    views.add_frame(T, K, dropped)
    views.add_frame(T, K, FAR)
    pts = np.array([[10, 0, 1], [5.1, 0, 1], [4.0, 0, 1]], dtype=np.float32)
    # Behind the wall: seen only by the clear frame; on the wall (within tolerance) and in
    # front of it: by the wall's frame and the clear one; never by the dropped frame.
    assert views.count(pts).tolist() == [1, 2, 2]


def test_incremental_views_equal_a_recount():
    from gate.views import ViewCounter
    rng = np.random.default_rng(0)
    views = ViewCounter(0.3, 20.0, tolerance_m=0.3)
    surface = rng.uniform([2, -5, -2], [15, 5, 3], (50, 3)).astype(np.float32)
    last_pred = None
    for _ in range(6):
        T = camera_looking_along_x(rng.uniform(-1, 1))
        depth = rng.uniform(3, 18, (K.height, K.width)).astype(np.float32)
        depth[rng.uniform(size=depth.shape) < 0.2] = np.nan
        views.add_frame(T, K, depth)
        surface = np.vstack([surface, rng.uniform([2, -5, -2], [15, 5, 3], (20, 3))]
                            ).astype(np.float32)
        pred = rng.uniform([2, -5, -2], [15, 5, 3], (40, 3)).astype(np.float32)
        if last_pred is not None:
            pred[:20] = last_pred[20:]  # half of it carried over from the last step
        last_pred = pred
        assert np.array_equal(views.views_grown("s", surface), views.count(surface))
        assert np.array_equal(views.views_keyed("p", pred), views.count(pred))


def _random_camera(rng, span_m):
    """A camera anywhere over a ``span_m`` square, at any heading, pitched a little."""
    T = camera_looking_along_x()
    yaw, pitch = rng.uniform(-np.pi, np.pi), rng.uniform(-0.4, 0.4)
    cy, sy, cp, sp = np.cos(yaw), np.sin(yaw), np.cos(pitch), np.sin(pitch)
    Rz = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]])
    Ry = np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
    T[:3, :3] = Rz @ Ry @ T[:3, :3]
    T[:3, 3] = [*rng.uniform(-span_m / 2, span_m / 2, 2), rng.uniform(0.5, 2.0)]
    return T


def test_views_counted_block_by_block_equal_every_frame_on_every_point():
    """The frustum culling (gate.views.Frustums, Blocks) changes no count: over a region
    much larger than a frustum, with points on block edges and cameras at any heading, the
    counts equal those of every frame projecting every point."""
    from gate.views import BLOCK_M, ViewCounter
    rng = np.random.default_rng(11)
    span = 120.0
    views = ViewCounter(0.3, 20.0, tolerance_m=0.3)
    frames, surface = [], np.zeros((0, 3), np.float32)
    for step in range(25):
        # Half the cameras near the last one (a traverse), half anywhere.
        T = _random_camera(rng, span if step % 2 else 30.0)
        depth = rng.uniform(3, 25, (K.height, K.width)).astype(np.float32)
        depth[rng.uniform(size=depth.shape) < 0.1] = np.nan
        depth[rng.uniform(size=depth.shape) < 0.1] = np.inf
        views.add_frame(T, K, depth)
        frames.append((T, depth))
        new = rng.uniform([-span / 2, -span / 2, -3], [span / 2, span / 2, 5], (400, 3))
        new[:50, :2] = np.round(new[:50, :2] / BLOCK_M) * BLOCK_M  # on the blocks' edges
        surface = np.vstack([surface, new]).astype(np.float32)
        expected = np.zeros(len(surface), dtype=np.int64)
        for Tf, d in frames:
            R = Tf[:3, :3].T
            idx, v, u, z = pixels(surface, R, -R @ Tf[:3, 3], K, 0.3, 20.0)
            expected[idx[d[v, u] >= z - 0.3]] += 1
        assert np.array_equal(views.views_grown("s", surface), expected), step
        assert np.array_equal(views.count(surface), expected), step
    assert expected.max() >= 2 and (expected == 0).mean() > 0.5  # the case is not empty


def test_exposures_counted_block_by_block_equal_every_frame_on_every_point():
    """The gates test a frame only against the points in blocks its frustum meets; over a
    region much larger than a frustum their counts equal every frame on every point."""
    from gate.filter import PoseGate, RayGate
    rng = np.random.default_rng(12)
    span = 120.0
    frustum, ray = make_gate(), RayGate(2, 0.5, 0.3, 20.0, 0.3, 80.0)
    pose = PoseGate(2, 0.5, 0.3, 20.0, sigmas=2.0)
    frames = []
    for step in range(30):
        T = _random_camera(rng, span if step % 2 else 30.0)
        depth = rng.uniform(3, 25, (K.height, K.width)).astype(np.float32)
        cov = np.diag([0.01, 0.01, 0.01, 1e-4, 1e-4, 1e-4])
        for g in (frustum, ray, pose):
            g.add_frame(T, K, depth, cov)
        frames.append((T, ray._frames[-1][3]))
    pts = rng.uniform([-span / 2, -span / 2, -3], [span / 2, span / 2, 5], (6000, 3))
    inside = np.zeros(len(pts), np.int32)
    passed = np.zeros(len(pts), np.int32)
    for T, usable in frames:
        R = T[:3, :3].T
        idx, v, u, z = pixels(pts, R, -R @ T[:3, 3], K, 0.3, 20.0)
        inside[idx] += 1
        passed[idx[usable[v, u] >= z + 0.3]] += 1
    assert np.array_equal(frustum.exposure_counts(pts), inside)
    assert np.array_equal(ray.exposure_counts(pts), passed)
    assert inside.max() >= 2 and passed.max() >= 2 and (inside == 0).mean() > 0.5
    full = PoseGate(2, 0.5, 0.3, 20.0, sigmas=2.0)  # the same frames, one block for all
    full._frustums.cull = False
    for T, _ in frames:
        full.add_frame(T, K, np.zeros((K.height, K.width), np.float32),
                       np.diag([0.01, 0.01, 0.01, 1e-4, 1e-4, 1e-4]))
    assert np.array_equal(pose.exposure_counts(pts), full.exposure_counts(pts))


def test_everything_the_planner_gets_lies_in_the_scored_region():
    ref = np.array([[0, 0, 0], [5, 5, 0]], dtype=np.float32)
    surface = np.array([[0, 0, 0.05], [12, 0, 0]], dtype=np.float32)     # one outside
    pred = np.array([[5, 5, 0.1], [0, 11, 0], [3, 3, 3]], dtype=np.float32)  # one outside
    bounds = (-10.0, -10.0, -5.0, 10.0, 10.0, 5.0)
    pose = Pose.from_matrix(camera_looking_along_x())
    for name in CONDITIONS:
        out = new_gate(name, ref, bounds).step(_mapped(surface, pred), pose, K, FAR)
        p = xyz(out.points)
        assert len(p) and (np.abs(p[:, :2]) <= 10).all(), name


# --- gated-ray: exposure only where the ray passed through the point ----------------------


def make_ray_gate(k=1, eps=0.5, margin=0.3, grazing=75.0, beyond_range_passes=False):
    from gate.filter import RayGate
    return RayGate(k=k, epsilon_m=eps, min_range_m=0.3, max_range_m=20.0, margin_m=margin,
                   grazing_max_deg=grazing, beyond_range_passes=beyond_range_passes)


def wall(distance: float) -> np.ndarray:
    """A depth image of a wall facing the camera ``distance`` metres ahead."""
    return np.full((K.height, K.width), distance, dtype=np.float32)


def test_a_ray_exposes_only_what_it_passed_through():
    """Points 4 m (in front of a wall at 5 m), 4.9 m (on it, within the margin), 5.1 and
    10 m (behind it) ahead: only the first is exposed; the frustum gate counts all four."""
    pts = np.array([[4.0, 0, 1], [4.9, 0, 1], [5.1, 0, 1], [10, 0, 1]], dtype=np.float32)
    ray, frustum = make_ray_gate(), make_gate()
    for g in (ray, frustum):
        g.add_frame(camera_looking_along_x(), K, wall(5.0))
    assert ray.exposure_counts(pts).tolist() == [1, 0, 0, 0]
    assert frustum.exposure_counts(pts).tolist() == [1, 1, 1, 1]


def test_dropped_saturated_and_out_of_range_returns_are_no_evidence():
    g = make_ray_gate()
    for depth in (np.nan, np.inf, -np.inf):
        g.add_frame(camera_looking_along_x(), K, wall(depth))
    pts = np.array([[4.0, 0, 1], [10, 0, 1]], dtype=np.float32)
    assert g.exposure_counts(pts).tolist() == [0, 0]
    g.add_frame(camera_looking_along_x(), K, wall(15.0))
    assert g.exposure_counts(pts).tolist() == [1, 1]
    assert g.exposure_counts(np.array([[25, 0, 1]], np.float32)).tolist() == [0]  # > range


def test_a_return_beyond_range_is_the_rays_passage_for_gated_ray_inf():
    """+Inf (nothing within range along the pixel) exposes every point nearer than the range;
    a dropped return (NaN) still exposes nothing, nor does a point beyond the range."""
    g = make_ray_gate(beyond_range_passes=True)
    pts = np.array([[4.0, 0, 1], [10, 0, 1]], dtype=np.float32)
    g.add_frame(camera_looking_along_x(), K, wall(np.nan))
    assert g.exposure_counts(pts).tolist() == [0, 0]
    g.add_frame(camera_looking_along_x(), K, wall(np.inf))
    assert g.exposure_counts(pts).tolist() == [1, 1]
    assert g.exposure_counts(np.array([[25, 0, 1]], np.float32)).tolist() == [0]  # > range
    # A point whose pixel is +Inf but beside a surface's silhouette: no evidence.
    edge = wall(np.inf)
    _, v, u, _ = pixels(pts[:1], *g._frames[-1][:3], 0.3, 20.0)
    edge[v[0], u[0] + 1] = 3.0
    h = make_ray_gate(beyond_range_passes=True)
    h.add_frame(camera_looking_along_x(), K, edge)
    assert h.exposure_counts(pts[:1]).tolist() == [0]
    # Sky beside a rock: the sky's pixels pass, the rock's edge (a depth discontinuity) and
    # the pixels behind the rock do not; the grazing test still reads the finite returns.
    half = wall(3.0)
    half[:, K.width // 2:] = np.inf
    usable = g.usable_depth(half, K)
    assert np.isposinf(usable[1:-1, K.width // 2 + 1:-1]).all()
    # Beside the rock's silhouette, and on the image's edge, +Inf is no evidence either.
    assert np.isnan(usable[:, K.width // 2]).all() and np.isnan(usable[:, -1]).all()
    assert np.isnan(usable[0, K.width // 2:]).all() and np.isnan(usable[-1, K.width // 2:]).all()
    assert np.isnan(usable[:, K.width // 2 - 1]).all()  # beside +Inf: no slope, no evidence
    assert (usable[:, :K.width // 2 - 1] == 3.0).all()
    plain = make_ray_gate().usable_depth(half, K)
    assert np.isnan(plain[:, K.width // 2:]).all()


def test_a_hallucinated_surface_against_the_sky_is_withheld_only_by_gated_ray_inf():
    """The frustum gate's correct removals: a prediction floating where every frame saw
    nothing within range. The ray gate never has evidence; with +Inf as passage it does."""
    floating = np.array([[6.0, 0, 1]], dtype=np.float32)
    no_surface = np.zeros((0, 3), np.float32)
    ray, inf_ray = make_ray_gate(k=2), make_ray_gate(k=2, beyond_range_passes=True)
    for x in (0.0, 0.5):
        for g in (ray, inf_ray):
            g.add_frame(camera_looking_along_x(x), K, wall(np.inf))
    assert ray.unsupported(floating, no_surface).tolist() == [False]
    assert inf_ray.unsupported(floating, no_surface).tolist() == [True]
    assert inf_ray.unsupported(floating, floating + [[0, 0.3, 0]]).tolist() == [False]


def test_a_grazing_return_is_no_evidence():
    """A floor seen almost edge-on: its returns change depth fast from row to row. With the
    grazing test on they give no evidence; with it off (90 degrees) they do."""
    rows = np.arange(K.height, dtype=np.float32)[:, None] - 24  # 0 at the point's row
    # 1 m more depth per row at 10 m: tan(angle) = 1 * 57.9 px / 10 m, 80 degrees.
    floor = np.broadcast_to(np.maximum(10.0 + rows, 0.5), (K.height, K.width)).astype(
        np.float32)
    point = np.array([[4.0, 0, 1]], dtype=np.float32)  # well in front of every return
    steep, off = make_ray_gate(grazing=75.0), make_ray_gate(grazing=90.0)
    for g in (steep, off):
        g.add_frame(camera_looking_along_x(), K, floor)
    assert steep.exposure_counts(point).tolist() == [0]
    assert off.exposure_counts(point).tolist() == [1]
    # 5 cm more per row at 10 m is 16 degrees: every return usable.
    gentle = np.broadcast_to(10.0 + 0.05 * rows, (K.height, K.width)).astype(np.float32)
    assert np.isfinite(make_ray_gate(grazing=75.0).usable_depth(gentle, K)).all()


def test_the_ray_gate_withholds_an_occluded_prediction_the_frustum_gate_drops():
    """A prediction hidden behind a rock in every frame: the frustum gate suppresses it after
    K frames although nothing ever looked at it; the ray gate keeps it."""
    hidden = np.array([[8.0, 0, 1]], dtype=np.float32)
    no_surface = np.zeros((0, 3), np.float32)
    ray, frustum = make_ray_gate(k=2), make_gate(k=2)
    for x in (0.0, 0.5, 1.0):
        for g in (ray, frustum):
            g.add_frame(camera_looking_along_x(x), K, wall(4.0 - x))
    assert frustum.unsupported(hidden, no_surface).tolist() == [True]
    assert ray.unsupported(hidden, no_surface).tolist() == [False]
    # Seen through twice (the rock gone), unsupported: suppressed; supported: kept.
    for _ in range(2):
        ray.add_frame(camera_looking_along_x(), K, wall(15.0))
    assert ray.unsupported(hidden, no_surface).tolist() == [True]
    assert ray.unsupported(hidden, hidden + [[0, 0.3, 0]]).tolist() == [False]


def test_ray_gate_equals_its_rule_computed_point_by_point():
    """The vectorised count and equation 4's shortcuts against the rule, one point and one
    frame at a time, on random frames with dropped, saturated and grazing returns."""
    from gate.filter import RayGate
    rng = np.random.default_rng(5)
    g = RayGate(k=2, epsilon_m=0.8, min_range_m=0.3, max_range_m=20.0, margin_m=0.3,
                grazing_max_deg=75.0)
    frames = []
    for yaw in rng.uniform(-0.5, 0.5, 12):
        T = camera_looking_along_x(rng.uniform(-1, 1))
        c, s_ = np.cos(yaw), np.sin(yaw)
        T[:3, :3] = np.array([[c, -s_, 0], [s_, c, 0], [0, 0, 1]]) @ T[:3, :3]
        depth = rng.uniform(2, 19, (K.height // 8, K.width // 8)).repeat(8, 0).repeat(8, 1)
        depth = depth.astype(np.float32)
        depth[rng.uniform(size=depth.shape) < 0.1] = np.nan
        depth[rng.uniform(size=depth.shape) < 0.05] = np.inf
        g.add_frame(T, K, depth)
        frames.append((T, depth))
    pts = rng.uniform([-2, -8, -3], [15, 8, 3], (1500, 3))
    surface = rng.uniform([-2, -8, -3], [15, 8, 3], (300, 3))
    tan_max = np.tan(np.radians(75.0))

    def usable(depth, v, u):
        d = depth[v, u]
        if not np.isfinite(d):
            return None
        gv, gu = np.gradient(np.where(np.isfinite(depth), depth, np.nan).astype(np.float64))
        t = np.hypot(gu[v, u] * K.fx, gv[v, u] * K.fy) / d
        return d if t <= tan_max else None  # a non-finite neighbour: NaN slope, unusable

    expected_counts = np.zeros(len(pts), dtype=int)
    for T, depth in frames:
        R = T[:3, :3].T
        for i, p in enumerate(pts):
            x, y, z = R @ (p - T[:3, 3])
            if not 0.3 <= z <= 20.0:
                continue
            u = int(np.floor(K.fx * x / z + K.cx + 0.5))
            v = int(np.floor(K.fy * y / z + K.cy + 0.5))
            if 0 <= u < K.width and 0 <= v < K.height:
                d = usable(depth, v, u)
                expected_counts[i] += d is not None and d >= z + 0.3
    assert np.array_equal(g.exposure_counts(pts), expected_counts)
    dist = np.min(np.linalg.norm(pts[:, None] - surface[None], axis=2), axis=1)
    expected = (expected_counts >= 2) & (dist > 0.8)
    assert 0 < expected.sum() < len(pts)
    assert np.array_equal(g.unsupported(pts, surface), expected)


def test_gated_ray_condition_withholds_through_the_ray_gate():
    gate = new_gate("gated-ray")  # epsilon 0.3 m, K 2
    pred = np.vstack([[[4.0, 0, 1]], [[8.0, 0, 1]]]).astype(np.float32)  # before / behind
    pose = Pose.from_matrix(camera_looking_along_x())
    no_surface = np.zeros((0, 3), np.float32)
    for _ in range(2):
        out = gate.step(_mapped(no_surface, pred), pose, K, wall(6.0))
    kept = out.points[out.points["source"] == Source.PREDICTED]
    assert out.suppressed == 1 and kept["x"].tolist() == [8.0]


# --- gated-pose: exposure and support under the pose's uncertainty -------------------------


def make_pose_gate(k=1, eps=0.5, sigmas=2.0):
    from gate.filter import PoseGate
    return PoseGate(k=k, epsilon_m=eps, min_range_m=0.3, max_range_m=20.0, sigmas=sigmas)


def cov(sd_pos: float, sd_yaw: float = 0.0) -> np.ndarray:
    return np.diag([sd_pos ** 2] * 3 + [0.0, 0.0, sd_yaw ** 2])


def test_without_uncertainty_the_pose_gate_is_the_frustum_gate():
    rng = np.random.default_rng(11)
    pose, frustum = make_pose_gate(k=2, eps=0.8), make_gate(k=2, eps=0.8)
    for x in rng.uniform(-1, 1, 20):
        for g in (pose, frustum):
            g.add_frame(camera_looking_along_x(x), K, FAR, np.zeros((6, 6)))
    pts = rng.uniform([-2, -8, -3], [22, 8, 3], (2000, 3))
    surface = rng.uniform([-2, -8, -3], [22, 8, 3], (300, 3))
    assert np.array_equal(pose.exposure_counts(pts), frustum.exposure_counts(pts))
    assert np.array_equal(pose.unsupported(pts, surface), frustum.unsupported(pts, surface))


def test_a_point_the_uncertain_pose_may_not_have_seen_is_not_exposed():
    """Near the image's edge, near the far range, or with a heading error wider than the
    margin to the edge: the frustum gate counts them; the pose gate does not."""
    half_width = 10.0 * np.tan(np.radians(45.0) / 2) * K.width / K.height  # at 10 m
    edge = np.array([[10.0, -(half_width - 0.2), 1.0]], dtype=np.float32)   # 0.2 m inside
    far = np.array([[19.8, 0.0, 1.0]], dtype=np.float32)
    for c, pts, counted in ((cov(0.2), edge, 0), (cov(0.2), far, 0), (cov(0.0, 0.05), edge, 0),
                            (cov(0.01), TARGET, 1)):
        g = make_pose_gate()
        g.add_frame(camera_looking_along_x(), K, FAR, c)
        assert g.exposure_counts(pts).tolist() == [counted], (c.diagonal(), pts)
        f = make_gate()
        f.add_frame(camera_looking_along_x(), K, FAR)
        assert f.exposure_counts(pts).tolist() == [1]


def test_pose_widened_support_keeps_what_a_drifted_frame_would_drop():
    """The surface lies 0.6 m from a predicted point (epsilon 0.5): the frustum gate drops
    the point; with a position standard deviation of 0.1 m (support within 0.5 + 2 x 0.1)
    the pose gate keeps it, and with none it drops it too."""
    surface = TARGET + np.array([[0.0, 0.6, 0.0]], dtype=np.float32)
    for sd, dropped in ((0.1, False), (0.0, True)):
        g = make_pose_gate(k=2)
        for _ in range(2):
            g.add_frame(camera_looking_along_x(), K, FAR, cov(sd))
        assert g.unsupported(TARGET, surface).tolist() == [dropped]
    f = make_gate(k=2)
    for _ in range(2):
        f.add_frame(camera_looking_along_x(), K, FAR)
    assert f.unsupported(TARGET, surface).tolist() == [True]


def test_pose_gate_equals_its_rule_computed_point_by_point():
    rng = np.random.default_rng(13)
    g = make_pose_gate(k=2, eps=0.8, sigmas=2.0)
    frames = []
    for _ in range(15):
        T = camera_looking_along_x(rng.uniform(-1, 1))
        c = cov(rng.uniform(0, 0.3), rng.uniform(0, 0.05))
        g.add_frame(T, K, FAR, c)
        frames.append((T, 2 * np.sqrt(c[0, 0]), 2 * np.sqrt(c[5, 5])))
    pts = rng.uniform([-2, -8, -3], [22, 8, 3], (1500, 3))
    surface = rng.uniform([-2, -8, -3], [22, 8, 3], (300, 3))
    expected_counts = np.zeros(len(pts), dtype=int)
    for T, r, a in frames:
        R = T[:3, :3].T
        for i, p in enumerate(pts):
            x, y, z = R @ (p - T[:3, 3])
            if not (z - r >= 0.3 and z + r <= 20.0):
                continue
            m = r / (z - r) + np.tan(a)
            u, v = K.fx * x / z + K.cx, K.fy * y / z + K.cy
            expected_counts[i] += (-0.5 + K.fx * m <= u < K.width - 0.5 - K.fx * m
                                   and -0.5 + K.fy * m <= v < K.height - 0.5 - K.fy * m)
    assert np.array_equal(g.exposure_counts(pts), expected_counts)
    radius = 0.8 + frames[-1][1]
    dist = np.min(np.linalg.norm(pts[:, None] - surface[None], axis=2), axis=1)
    expected = (expected_counts >= 2) & (dist > radius)
    assert 0 < expected.sum() < len(pts)
    assert np.array_equal(g.unsupported(pts, surface), expected)


# --- gated-split: separate evidence for the gain and the collision channel ------------------


def make_split_gate(k=2, eps=0.5, baseline=0.5):
    from gate.filter import SplitGate
    return SplitGate(k=k, epsilon_m=eps, min_range_m=0.3, max_range_m=20.0, margin_m=0.3,
                     grazing_max_deg=75.0, baseline_m=baseline)


def test_split_channels_need_two_places_to_unblock():
    """Seen through twice from one place: the point attracts no longer (gain withheld) but
    still blocks; seen through from a second place 1 m away: withheld from both; with
    support: from neither."""
    point = np.array([[8.0, 0.0, 1.0]], dtype=np.float32)
    no_surface = np.zeros((0, 3), np.float32)
    g = make_split_gate()
    for _ in range(2):
        g.add_frame(camera_looking_along_x(0.0), K, wall(15.0))
    gain, collision = g.withheld(point, no_surface)
    assert (gain.tolist(), collision.tolist()) == ([True], [False])
    g.add_frame(camera_looking_along_x(1.0), K, wall(15.0))
    gain, collision = g.withheld(point, no_surface)
    assert (gain.tolist(), collision.tolist()) == ([True], [True])
    gain, collision = g.withheld(point, point + [[0, 0.2, 0]])
    assert (gain.tolist(), collision.tolist()) == ([False], [False])
    # An occluded point is never seen through, from anywhere.
    hidden = make_split_gate()
    for x in (0.0, 1.0, 2.0):
        hidden.add_frame(camera_looking_along_x(x), K, wall(5.0 - x))
    assert [m.tolist() for m in hidden.withheld(point, no_surface)] == [[False], [False]]


def test_split_gate_equals_its_rule_computed_point_by_point():
    rng = np.random.default_rng(17)
    g = make_split_gate(k=2, eps=0.8, baseline=0.8)
    frames = []
    for _ in range(10):
        T = camera_looking_along_x(rng.uniform(-1, 1))
        depth = rng.uniform(2, 19, (K.height // 8, K.width // 8)).repeat(8, 0).repeat(8, 1)
        g.add_frame(T, K, depth.astype(np.float32))
        frames.append(T)
    pts = rng.uniform([-2, -8, -3], [15, 8, 3], (800, 3))
    surface = rng.uniform([-2, -8, -3], [15, 8, 3], (200, 3))
    dist = np.min(np.linalg.norm(pts[:, None] - surface[None], axis=2), axis=1)
    centres = []
    for i in range(len(pts)):
        centres.append([T[:3, 3] for f, T in enumerate(frames)
                        if len(g._passed(f, pts[i:i + 1]))])
    two = np.array([any(np.linalg.norm(a - b) >= 0.8 for a in c for b in c) for c in centres])
    gain, collision = g.withheld(pts, surface)
    assert np.array_equal(gain, (np.array([len(c) for c in centres]) >= 2) & (dist > 0.8))
    assert np.array_equal(collision, two & (dist > 0.8))
    assert 0 < collision.sum() < gain.sum()


def test_gated_split_marks_each_point_with_the_channels_it_serves():
    gate = new_gate("gated-split")  # epsilon 0.3 m, K 2, baseline 0.5 m
    pred = np.array([[8.0, 0, 1], [8.0, 3.0, 1]], dtype=np.float32)
    no_surface = np.zeros((0, 3), np.float32)
    for x in (0.0, 0.0):
        out = gate.step(_mapped(no_surface, pred), Pose.from_matrix(camera_looking_along_x(x)),
                        K, wall(15.0))
    predicted = out.points[out.points["source"] == Source.PREDICTED]
    assert predicted["channels"].tolist() == [Channel.COLLISION, Channel.COLLISION]
    assert out.suppressed == 2
    assert len(out.serving(Channel.GAIN).points) == len(out.points) - 2
    assert len(out.serving(Channel.COLLISION).points) == len(out.points)


def test_the_incremental_support_test_is_the_brute_force_one_step_after_step():
    """SurfaceSupport against min ||x - p|| <= radius over a surface that grows at its end,
    predictions that partly repeat, a radius that grows and shrinks, and a surface that
    starts over (not an extension: as after a restart)."""
    from gate.filter import SurfaceSupport
    rng = np.random.default_rng(3)
    support = SurfaceSupport()
    support.REBUILD_MIN = 50  # rebuild the prefix's tree often, keep a tail too
    surface = np.zeros((0, 3), np.float32)
    predicted = rng.uniform(0, 10, (400, 3)).astype(np.float32)
    radii = [0.5, 0.5, 0.8, 0.8, 0.4, 0.4, 1.0, 1.0, 1.0, 0.6]
    for step, radius in enumerate(radii):
        if step == 7:
            surface = rng.uniform(0, 10, (30, 3)).astype(np.float32)  # starts over
        else:
            surface = np.vstack([surface, rng.uniform(0, 10, (40 + 20 * step, 3))]
                                ).astype(np.float32)
        keep = rng.random(len(predicted)) < 0.7  # 70% repeat, the rest are new
        predicted = np.vstack([predicted[keep], rng.uniform(0, 10, (int((~keep).sum()), 3))]
                              ).astype(np.float32)
        got = support.supported(predicted, surface, radius)
        d = np.linalg.norm(predicted[:, None].astype(np.float64) - surface[None], axis=2)
        assert np.array_equal(got, d.min(axis=1) <= radius), step
        assert 0 < got.sum() < len(predicted), step  # both kinds occur
    assert not support.supported(predicted, surface[:0], 1.0).any()
    # A surface that loses its tail, or has it rewritten, forgets the support it gave.
    fresh = SurfaceSupport()
    prefix = rng.uniform(0, 10, (3000, 3)).astype(np.float32)
    x = np.array([[20.0, 20.0, 20.0]], np.float32)
    assert fresh.supported(x, np.vstack([prefix, x + 0.1]), 0.5).tolist() == [True]
    assert fresh.supported(x, prefix, 0.5).tolist() == [False]
    assert fresh.supported(x, np.vstack([prefix, x + 0.1]), 0.5).tolist() == [True]
    assert fresh.supported(x, np.vstack([prefix, x + 3.0]), 0.5).tolist() == [False]
