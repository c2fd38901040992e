"""Known free space: where the platform has seen, or been, that nothing is.

The planner-facing map holds what is occupied; it says nothing of space no camera has looked
at. A flyer that treats that space as free flies backwards into walls its camera never saw. So
the flyer moves only through space known to be free: a voxel (``voxel_m``) is known free once a
frame's ray passed through it on its way to a return farther on (+Inf, nothing within range,
counts), or once the platform's own body has occupied it. An invalid return (NaN:
dropped, too near) is no evidence. The map's points still decide clearance; this decides where
the unknown begins.

The grid covers the scored region's footprint, from one metre below the box of interest to the
flyer's ceiling above it. Each frame carves along its rays (a ray sampled every 0.8 voxel,
stopping a voxel's half-diagonal short of its return), as the mapper's own grid does.
"""

from __future__ import annotations

import math

import numpy as np

from rovergate.types import CameraIntrinsics

RAY_STRIDE_PX = 4
"""Carve along the rays of every fourth pixel in each direction (about 0.25 m apart at 10 m,
one voxel)."""
CARVE_RANGE_M = 10.0
"""Carve at most this far from the camera per frame (the platform moves a few metres a step;
farther space is carved when it comes nearer)."""


class FreeSpace:
    """A boolean voxel grid of known free space (see the module docstring)."""

    def __init__(self, box: tuple[float, ...], voxel_m: float, min_range_m: float,
                 max_range_m: float) -> None:
        self.lo = np.array(box[:3], dtype=np.float64)
        self.voxel = voxel_m
        self.shape = tuple(int(math.ceil((box[i + 3] - box[i]) / voxel_m)) for i in range(3))
        self.free = np.zeros(self.shape, dtype=bool)
        self.min_range_m, self.max_range_m = min_range_m, max_range_m
        self._lo = tuple(float(v) for v in self.lo)
        self._margin = voxel_m * math.sqrt(3) / 2  # a voxel's half-diagonal short of the return

    def add_frame(self, T_map_camera: np.ndarray, k: CameraIntrinsics, depth: np.ndarray
                  ) -> None:
        """Carve what one frame saw to be empty: along the rays of every ``RAY_STRIDE_PX``-th
        pixel, every 0.8 voxel, up to a voxel short of the return (or to ``CARVE_RANGE_M``)."""
        d = np.asarray(depth, dtype=np.float64)[::RAY_STRIDE_PX, ::RAY_STRIDE_PX]
        v, u = np.nonzero(d > self.min_range_m)  # NaN (no evidence) compares False
        if len(v) == 0:
            return
        reach = np.minimum(d[v, u] - self._margin, min(self.max_range_m, CARVE_RANGE_M))
        u, v = u * RAY_STRIDE_PX, v * RAY_STRIDE_PX
        # Unit rays in the camera frame (z forward), then in the map.
        ray = np.stack([(u - k.cx) / k.fx, (v - k.cy) / k.fy, np.ones(len(u))], axis=1)
        ray /= np.linalg.norm(ray, axis=1, keepdims=True)
        ray = ray @ T_map_camera[:3, :3].T
        # A ray's depth z is its length times its z component: carve to reach in depth.
        length = reach / (ray @ T_map_camera[:3, :3][:, 2])
        step = 0.8 * self.voxel
        t = np.arange(int(np.ceil(length.max() / step)) + 1) * step
        rows, cols = np.nonzero(t[None, :] < length[:, None])
        # In voxel units, one axis at a time (float32 is exact enough at a voxel's scale).
        o = ((T_map_camera[:3, 3] - self.lo) / self.voxel).astype(np.float32)
        r = (ray / self.voxel).astype(np.float32)
        tc = t.astype(np.float32)[cols]
        flat = np.zeros(len(rows), dtype=np.int64)
        ok = np.ones(len(rows), dtype=bool)
        for axis in range(3):
            i = np.floor(o[axis] + r[rows, axis] * tc).astype(np.int64)
            ok &= (i >= 0) & (i < self.shape[axis])
            flat = flat * self.shape[axis] + i
        self.free.reshape(-1)[flat[ok]] = True

    def add_body(self, position: np.ndarray, radius_m: float) -> None:
        """Carve the voxels whose centre the body (a sphere of ``radius_m``) occupies."""
        p = np.asarray(position, dtype=np.float64)
        lo = np.clip(np.floor((p - radius_m - self.lo) / self.voxel).astype(int), 0, self.shape)
        hi = np.clip(np.ceil((p + radius_m - self.lo) / self.voxel).astype(int) + 1, 0,
                     self.shape)
        if np.any(hi <= lo):
            return
        ijk = np.stack(np.meshgrid(*[np.arange(lo[i], hi[i]) for i in range(3)],
                                   indexing="ij"), axis=-1).reshape(-1, 3)
        c = self.lo + (ijk + 0.5) * self.voxel
        inside = np.sum((c - p) ** 2, axis=1) <= radius_m**2
        self.free[ijk[inside, 0], ijk[inside, 1], ijk[inside, 2]] = True

    def is_free(self, x: float, y: float, z: float) -> bool:
        """Whether the voxel holding (x, y, z) is known free (outside the grid: no)."""
        i = math.floor((x - self._lo[0]) / self.voxel)
        j = math.floor((y - self._lo[1]) / self.voxel)
        k = math.floor((z - self._lo[2]) / self.voxel)
        s = self.shape
        return 0 <= i < s[0] and 0 <= j < s[1] and 0 <= k < s[2] and bool(self.free[i, j, k])

    def free_many(self, xyz: np.ndarray) -> np.ndarray:
        """(N,) bool: :meth:`is_free` of many positions."""
        ijk = np.floor((np.asarray(xyz, dtype=np.float64) - self.lo) / self.voxel).astype(int)
        ok = np.all((ijk >= 0) & (ijk < self.shape), axis=1)
        out = np.zeros(len(ijk), dtype=bool)
        out[ok] = self.free[ijk[ok, 0], ijk[ok, 1], ijk[ok, 2]]
        return out
