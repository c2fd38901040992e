"""Rendered surface gain: how many novel map points a candidate view would see.

The planner-facing map is first gathered into primitives, as MAGICIAN renders Gaussians rather
than raw points: one primitive per ``voxel_m`` voxel that holds map points, at their centroid,
weighted by how many of them are novel. A candidate view projects the primitives at a reduced
resolution; a per-pixel z-buffer keeps the nearest depth, and a primitive counts as visible
when it lies at most ``tolerance_m`` behind that nearest depth (so a surface's own primitives
do not hide each other, while a wall hides what is behind it); the z-buffer is eroded by one
pixel to close the gaps between samples. Gain is the novel weight of the visible primitives.

Cumulative gain along a trajectory counts each primitive once: :meth:`GainField.visible` gives
the primitives a view sees, and the search keeps the union of what its earlier views saw.
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


class GainField:
    """One step's planner-facing map as weighted primitives, ready to render from any view."""

    def __init__(self, points_map: np.ndarray, novel: np.ndarray, voxel_m: float,
                 k: CameraIntrinsics, min_range_m: float, max_range_m: float,
                 tolerance_m: float) -> None:
        self.k = k
        self.min_range_m, self.max_range_m, self.tolerance_m = min_range_m, max_range_m, tolerance_m
        p = np.asarray(points_map, dtype=np.float64)
        if len(p) == 0:
            self.centres = np.zeros((0, 3))
            self.weight = np.zeros(0, dtype=np.int64)
            return
        ijk = np.floor(p / voxel_m).astype(np.int64)
        ijk -= ijk.min(axis=0)
        span = ijk.max(axis=0) + 1
        keys = (ijk[:, 0] * span[1] + ijk[:, 1]) * span[2] + ijk[:, 2]
        _, inverse, count = np.unique(keys, return_inverse=True, return_counts=True)
        self.centres = np.stack([np.bincount(inverse, weights=p[:, i]) for i in range(3)],
                                axis=1) / count[:, None]
        self.weight = np.bincount(inverse, weights=novel.astype(np.float64)).astype(np.int64)

    def __len__(self) -> int:
        return len(self.centres)

    def visible(self, T_map_camera: np.ndarray) -> np.ndarray:
        """Indices of the primitives a camera at ``T_map_camera`` sees."""
        return np.flatnonzero(visible_mask(self.centres, T_map_camera, self.k, self.min_range_m,
                                           self.max_range_m, self.tolerance_m))

    def gain(self, visible: np.ndarray, seen: np.ndarray | None = None) -> int:
        """Novel weight of the ``visible`` primitives not already in ``seen`` (bool mask)."""
        if seen is not None:
            visible = visible[~seen[visible]]
        return int(self.weight[visible].sum())


def render_gain(points_map: np.ndarray, novel: np.ndarray, cameras: list[np.ndarray],
                k: CameraIntrinsics, min_range_m: float, max_range_m: float,
                tolerance_m: float, voxel_m: float) -> np.ndarray:
    """(C,) int64 novel weight each candidate camera would see (see :class:`GainField`)."""
    gains = np.zeros(len(cameras), dtype=np.int64)
    if not novel.any():
        return gains
    field = GainField(points_map, novel, voxel_m, k, min_range_m, max_range_m, tolerance_m)
    for i, T in enumerate(cameras):
        gains[i] = field.gain(field.visible(T))
    return gains
