"""Geometry every module shares: where the camera sits on each platform, and the voxel keys
that S_t, the reference occupancy O* and the audit agree on (rotations and quaternions are
:mod:`rovergate.rotations`, re-exported here).

Two platforms: ``rover`` (SE(2) on the terrain; the camera on a pan-tilt mast) and ``flyer``
(a free camera; its body pose is the camera's, heading and pitch included).
"""

from __future__ import annotations

import numpy as np

from rovergate.config import HazcamConfig, SensorConfig
from rovergate.platforms import get_platform
from rovergate.rotations import (  # noqa: F401 (re-exported: every caller's one module)
    matrix_to_quat,
    quat_to_matrix,
    quat_to_yaw,
    rot_x,
    rot_y,
    rot_z,
    yaw_to_quat,
)
from rovergate.types import CameraIntrinsics

_OFFSET = 1 << 20  # voxel indices are shifted into [0, 2^21) so they pack into one int64


#: Optical frame (x right, y down, z forward) expressed in a body frame (x fwd, y left, z up).
R_BODY_OPTICAL = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


def camera_from_base(T_map_base: np.ndarray, sensor: SensorConfig,
                     platform: str = "rover", look_deg: float = 0.0) -> np.ndarray:
    """(4, 4) optical-frame pose of the camera for a base pose of ``platform``; the rover's
    mast panned ``look_deg`` (left positive) beyond its mounting's ``pan_deg``."""
    if get_platform(platform).flies:  # the camera is the body
        T = T_map_base.copy()
        T[:3, :3] = T_map_base[:3, :3] @ R_BODY_OPTICAL
        return T
    T_base_mast = np.eye(4)
    T_base_mast[:3, :3] = (rot_z(np.radians(sensor.pan_deg + look_deg))
                           @ rot_y(-np.radians(sensor.tilt_deg)))
    T_base_mast[:3, 3] = [sensor.mast_forward_m, 0.0, sensor.mast_height_m]
    T_mast_optical = np.eye(4)
    T_mast_optical[:3, :3] = R_BODY_OPTICAL
    return T_map_base @ T_base_mast @ T_mast_optical


#: The rover's hazard cameras, by the name their topics and optical frames carry.
HAZCAMS = ("front", "rear")


def hazcam_from_base(T_map_base: np.ndarray, hazcam: HazcamConfig, which: str) -> np.ndarray:
    """(4, 4) optical-frame pose of the ``front`` or ``rear`` hazard camera for a rover base
    pose: ``forward_m`` ahead of (behind) the centre, ``height_m`` up, facing out of that end
    of the body and tilted ``tilt_deg`` (negative: down)."""
    back = {"front": False, "rear": True}[which]
    T_base_cam = np.eye(4)
    T_base_cam[:3, :3] = (rot_z(np.pi if back else 0.0) @ rot_y(-np.radians(hazcam.tilt_deg))
                          @ R_BODY_OPTICAL)
    T_base_cam[:3, 3] = [-hazcam.forward_m if back else hazcam.forward_m, 0.0, hazcam.height_m]
    return T_map_base @ T_base_cam


def wrap_angle(a: float) -> float:
    """``a`` in [-pi, pi)."""
    return float((a + np.pi) % (2 * np.pi) - np.pi)


def densify_se2(poses: list[tuple[float, ...]], spacing_m: float,
                max_turn_rad: float = np.radians(5.0)) -> list[tuple[float, float, float]]:
    """The poses along straight SE(2) motions through ``poses`` (x, y and heading together,
    as OMPL interpolates them and the simulator executes them), at most ``spacing_m`` and
    ``max_turn_rad`` apart, the first pose included."""
    x, y, a = poses[0][:3]
    out = [(x, y, a)]
    for (x0, y0, a0), (x1, y1, a1) in zip([p[:3] for p in poses[:-1]],
                                          [p[:3] for p in poses[1:]], strict=True):
        da = wrap_angle(a1 - a0)
        n = max(1, int(np.ceil(max(np.hypot(x1 - x0, y1 - y0) / spacing_m,
                                   abs(da) / max_turn_rad))))
        for k in range(1, n + 1):
            f = k / n
            out.append((x0 + f * (x1 - x0), y0 + f * (y1 - y0), wrap_angle(a0 + f * da)))
    return out


def in_region(points: np.ndarray, bounds_m: tuple[float, ...]) -> np.ndarray:
    """(N,) bool: the points over the footprint of the box of interest ``bounds_m``.

    This is the one scored region: the coverage samples and O* are drawn in it, and the gate
    crops everything it gives the planner (S_t, predictions, oracle points) to it, so that the
    gain, the oracle tags and the audit count the same surface as coverage does. The box's
    z range is not used, as the samples are not (a tall rock counts whole).
    """
    p = np.asarray(points)
    return ((p[:, 0] >= bounds_m[0]) & (p[:, 0] <= bounds_m[3]) & (p[:, 1] >= bounds_m[1])
            & (p[:, 1] <= bounds_m[4]))


def voxel_keys(points: np.ndarray, voxel_m: float) -> np.ndarray:
    """(N,) int64 key of the voxel that holds each point."""
    idx = np.floor(points.astype(np.float64) / voxel_m).astype(np.int64) + _OFFSET
    return (idx[:, 0] << 42) | (idx[:, 1] << 21) | idx[:, 2]


def voxel_first_points(points: np.ndarray, voxel_m: float) -> np.ndarray:
    """The first point of each occupied voxel, in order of first appearance."""
    _, first = np.unique(voxel_keys(points, voxel_m), return_index=True)
    return points[np.sort(first)]


def voxel_centres(keys: np.ndarray, voxel_m: float) -> np.ndarray:
    """(N, 3) float64 centre of each voxel of :func:`voxel_keys`."""
    mask = (1 << 21) - 1
    idx = np.stack([(keys >> 42) & mask, (keys >> 21) & mask, keys & mask], axis=1) - _OFFSET
    return (idx + 0.5) * voxel_m


def frustum_halfspaces(k: CameraIntrinsics, min_range_m: float, max_range_m: float
                       ) -> tuple[np.ndarray, np.ndarray] | None:
    """Where :func:`project` may find a point, as half-spaces ``n . p >= b`` of the camera's
    optical frame: ``(normals (6, 3), b (6,))``, unit inward normals. The range limits in z,
    and the side planes through the optical centre; a pixel's centre at u = fx x / z + cx is in
    the image for u in [-0.5, width - 0.5), and the planes stand a pixel further out on every
    side, so a test against them only ever keeps too much. None when ``min_range_m <= 0``:
    the side planes bound the frustum only in front of the camera."""
    if min_range_m <= 0:
        return None
    sides = np.array([[k.fx, 0.0, k.cx + 1.5], [-k.fx, 0.0, k.width + 0.5 - k.cx],
                      [0.0, k.fy, k.cy + 1.5], [0.0, -k.fy, k.height + 0.5 - k.cy]])
    sides /= np.linalg.norm(sides, axis=1, keepdims=True)
    normals = np.vstack([[[0.0, 0.0, 1.0], [0.0, 0.0, -1.0]], sides])
    return normals, np.array([min_range_m, -max_range_m, 0.0, 0.0, 0.0, 0.0])


def halfspaces_in_map(T_map_camera: np.ndarray, halfspaces: tuple[np.ndarray, np.ndarray]
                      ) -> tuple[np.ndarray, np.ndarray]:
    """:func:`frustum_halfspaces` of a camera at ``T_map_camera``, in the map frame:
    ``(m (3, 6), off (6,))`` with a map point inside only if ``p @ m >= off``."""
    normals, b = halfspaces
    m = T_map_camera[:3, :3] @ normals.T
    return m, T_map_camera[:3, 3] @ m + b


#: One intrinsic of a camera, or of each of a stack of frames (see :func:`project`).
Intrinsic = float | np.ndarray


def pixels_of(points_cam: np.ndarray, k: CameraIntrinsics, min_range_m: float,
              max_range_m: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Where a camera sees (N, 3) points given in its optical frame: ``(idx, v, u, z)`` of
    those in front of it within range that land on a pixel (the nearest), with their row,
    column and depth along the optical axis. The gain's z-buffer, the views and the gates
    all project through :func:`project`."""
    ok, v, u, z = project(points_cam, k.fx, k.fy, k.cx, k.cy, k.width, k.height,
                          min_range_m, max_range_m)
    idx = np.flatnonzero(ok)
    return idx, v[idx], u[idx], z[idx]


def project(points_cam: np.ndarray, fx: Intrinsic, fy: Intrinsic, cx: Intrinsic,
            cy: Intrinsic, width: Intrinsic, height: Intrinsic, min_range_m: float,
            max_range_m: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The one pinhole projection: ``(ok, v, u, z)`` of (..., 3) points in a camera's optical
    frame, ``ok`` where a point lies in front of it within range and lands on a pixel (the
    nearest: row ``v``, column ``u``), ``z`` its depth along the optical axis. The intrinsics
    are numbers, or arrays that broadcast against ``points_cam[..., 0]`` (one row per frame:
    the gate counts a chunk of frames at once)."""
    z = points_cam[..., 2]
    ok = (z >= min_range_m) & (z <= max_range_m)
    zs = np.where(ok, z, 1.0)
    u = np.floor(fx * points_cam[..., 0] / zs + cx + 0.5).astype(np.int64)
    v = np.floor(fy * points_cam[..., 1] / zs + cy + 0.5).astype(np.int64)
    ok &= (u >= 0) & (u < width) & (v >= 0) & (v < height)
    return ok, v, u, z
