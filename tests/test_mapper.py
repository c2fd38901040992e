"""Depth integration: back-projection and the voxel surface."""

from __future__ import annotations

import numpy as np

from mapper.integrate import VoxelSurface, backproject
from mapper.mapper import Mapper
from rovergate.config import MapperConfig
from rovergate.geometry import R_BODY_OPTICAL, voxel_first_points
from rovergate.types import CameraIntrinsics, Pose, SensorFrame


def test_backprojection_of_a_wall_lands_on_the_wall():
    k = CameraIntrinsics.from_fov(32, 24, 60.0)
    depth = np.full((24, 32), 4.0, dtype=np.float32)
    depth[0, 0] = np.nan
    T = np.eye(4)
    T[:3, :3] = R_BODY_OPTICAL  # looking along +x from (1, 2, 3)
    T[:3, 3] = [1.0, 2.0, 3.0]
    pts = backproject(depth, k, T)
    assert pts.shape == (24 * 32 - 1, 3) and pts.dtype == np.float32
    np.testing.assert_allclose(pts[:, 0], 5.0, atol=1e-5)
    # The optical axis passes through the image centre.
    assert abs(pts[:, 1].mean() - 2.0) < 0.1 and abs(pts[:, 2].mean() - 3.0) < 0.1


def test_voxel_surface_appends_and_counts_views():
    s = VoxelSurface(voxel_m=1.0)
    a = np.array([[0.1, 0.1, 0.1], [0.2, 0.2, 0.2], [5.5, 0, 0]], dtype=np.float32)
    assert s.integrate(a) == 2
    first = s.points.copy()
    b = np.array([[0.9, 0.9, 0.9], [-3.5, 0, 0]], dtype=np.float32)
    assert s.integrate(b) == 1
    np.testing.assert_array_equal(s.points[:2], first)  # earlier S_t is a prefix
    assert s.views.tolist() == [2, 1, 1]
    np.testing.assert_array_equal(s.points[0], a[0])  # the first point of a voxel stays


def test_voxel_surface_is_a_first_point_per_voxel_over_many_frames_and_merges():
    # Against the plain definition, a dict of voxel -> (first point, frames that saw it):
    # hundreds of overlapping frames, so the index's recent keys merge into its main run
    # many times; the points come out in the order voxels were first seen.
    from rovergate.geometry import voxel_keys
    rng = np.random.default_rng(11)
    s = VoxelSurface(voxel_m=0.5)
    first: dict[int, int] = {}
    points: list[np.ndarray] = []
    views: list[int] = []
    for frame in range(300):
        centre = rng.uniform(-2, 2, 3) + [0.3 * frame, 0, 0]  # a camera moving on
        pts = (centre + rng.normal(0, 2.0, (int(rng.integers(0, 400)), 3))).astype(np.float32)
        new = s.integrate(pts)
        made = 0
        keys = voxel_keys(pts, 0.5) if len(pts) else np.zeros(0, dtype=np.int64)
        for key in dict.fromkeys(keys.tolist()):  # each voxel once a frame
            if key in first:
                views[first[key]] += 1
            else:
                first[key] = len(points)
                points.append(pts[int(np.flatnonzero(keys == key)[0])])
                views.append(1)
                made += 1
        assert new == made
    assert len(s) == len(points) > 5_000
    np.testing.assert_array_equal(s.points, np.array(points))
    assert s.views.tolist() == views


def test_voxel_first_points_keeps_order():
    pts = np.array([[0.1, 0, 0], [3.2, 0, 0], [0.3, 0, 0]], dtype=np.float32)
    assert voxel_first_points(pts, 1.0).tolist() == pts[:2].tolist()


def test_mapper_without_a_model_publishes_an_empty_prediction():
    """Conditions that do not use the prediction (obs, truth) do not run the model."""
    k = CameraIntrinsics.from_fov(8, 6, 45.0)
    T = Pose.from_xyz_yaw(0, 0, 1, 0)
    frame = SensorFrame(0, np.full((6, 8), 2.0, np.float32), k, T, T)
    out = Mapper(MapperConfig()).step(frame)
    assert len(out.surface) > 0 and len(out.predicted) == 0
