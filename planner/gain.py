"""Rendered surface gain: how many novel map points a candidate view would see.

Points are projected into the candidate camera at a reduced resolution; a per-pixel z-buffer
keeps the nearest depth, and a point counts as visible when it lies at most
``tolerance_m`` behind that nearest depth (so a surface's own points do not hide each other,
while a wall hides what is behind it); the z-buffer is eroded by one pixel to close the gaps
between point samples. Gain is the number of visible novel points.
"""

from __future__ import annotations

import numpy as np
from scipy.ndimage import minimum_filter

from rovergate.types import CameraIntrinsics


def visible_mask(points_map: np.ndarray, T_map_camera: np.ndarray, k: CameraIntrinsics,
                 min_range_m: float, max_range_m: float, tolerance_m: float) -> np.ndarray:
    """(N,) bool: the points a camera at ``T_map_camera`` sees, with occlusion."""
    R, t = T_map_camera[:3, :3], T_map_camera[:3, 3]
    pc = (points_map.astype(np.float64) - t) @ R
    z = pc[:, 2]
    ok = (z >= min_range_m) & (z <= max_range_m)
    zs = np.where(ok, z, 1.0)
    u = np.floor(k.fx * pc[:, 0] / zs + k.cx + 0.5).astype(np.int64)
    v = np.floor(k.fy * pc[:, 1] / zs + k.cy + 0.5).astype(np.int64)
    ok &= (u >= 0) & (u < k.width) & (v >= 0) & (v < k.height)
    idx = np.flatnonzero(ok)
    visible = np.zeros(len(points_map), dtype=bool)
    if len(idx) == 0:
        return visible
    pix = v[idx] * k.width + u[idx]
    zbuf = np.full(k.width * k.height, np.inf)
    np.minimum.at(zbuf, pix, z[idx])
    # Points are samples, not surfaces: close the one-pixel gaps between the samples of a
    # near surface so that it hides what is behind it.
    zbuf = minimum_filter(zbuf.reshape(k.height, k.width), size=3, mode="nearest").ravel()
    visible[idx] = z[idx] <= zbuf[pix] + tolerance_m
    return visible


def render_gain(points_map: np.ndarray, novel: np.ndarray, cameras: list[np.ndarray],
                k: CameraIntrinsics, min_range_m: float, max_range_m: float,
                tolerance_m: float) -> np.ndarray:
    """(C,) int64 number of novel points each candidate camera would see."""
    gains = np.zeros(len(cameras), dtype=np.int64)
    if not novel.any():
        return gains
    for i, T in enumerate(cameras):
        # Cheap cull: only points within range of the camera can be seen.
        near = np.flatnonzero(np.sum((points_map - T[:3, 3]) ** 2, axis=1) <= max_range_m**2)
        vis = visible_mask(points_map[near], T, k, min_range_m, max_range_m, tolerance_m)
        gains[i] = int(np.count_nonzero(vis & novel[near]))
    return gains
