"""The mapper's voxel grid of what depth has shown: occupied, free (a ray passed) or unknown.

This is the learned model's input. The grid is dense over the mission's box of interest plus
margins (a rover's working area is tens of metres, so a few million bytes), at the model's
voxel size. A voxel is *occupied* once a depth return fell in it and *free* once a ray passed
through it without ending there; occupied wins over free, and a voxel no ray reached stays
*unknown*. Missing returns (NaN pixels: dropout, sky, out of range) give no free space: an
absent measurement is not evidence of emptiness.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mapper.integrate import backproject
from rovergate.types import CameraIntrinsics

FREE = np.uint8(1)
OCCUPIED = np.uint8(2)

#: Margins of the grid around the box of interest: the camera sees beyond the box.
MARGIN_XY_M = 10.0
MARGIN_BELOW_M = 4.0
MARGIN_ABOVE_M = 8.0


@dataclass(frozen=True)
class GridSpec:
    """A dense voxel grid: voxel (i, j, k) spans ``origin + [i, j, k] * voxel_m`` + one voxel."""

    origin_m: tuple[float, float, float]
    voxel_m: float
    shape: tuple[int, int, int]

    @classmethod
    def around(cls, bounds_m: tuple[float, ...], voxel_m: float) -> GridSpec:
        """The grid over a box of interest (xmin, ymin, zmin, xmax, ymax, zmax) with margins."""
        lo = np.array(bounds_m[:3], dtype=np.float64) - [MARGIN_XY_M, MARGIN_XY_M,
                                                          MARGIN_BELOW_M]
        hi = np.array(bounds_m[3:], dtype=np.float64) + [MARGIN_XY_M, MARGIN_XY_M,
                                                          MARGIN_ABOVE_M]
        lo = np.floor(lo / voxel_m) * voxel_m  # voxel-aligned: the same world voxels always
        shape = np.ceil((hi - lo) / voxel_m).astype(int)
        return cls(tuple(float(v) for v in lo), float(voxel_m), tuple(int(v) for v in shape))

    def index(self, points_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(N, 3) int64 voxel indices of map points, and the (N,) mask of those in the grid."""
        ijk = np.floor((np.asarray(points_m, np.float64) - self.origin_m)
                       / self.voxel_m).astype(np.int64)
        return ijk, self.inside(ijk[:, 0], ijk[:, 1], ijk[:, 2])

    def inside(self, i: np.ndarray, j: np.ndarray, k: np.ndarray) -> np.ndarray:
        """(N,) bool: whether voxel indices (i, j, k), one array per axis, are in the grid (a
        comparison per axis: numpy reduces an (N, 3) array along its short axis slowly)."""
        nx, ny, nz = self.shape
        return (i >= 0) & (i < nx) & (j >= 0) & (j < ny) & (k >= 0) & (k < nz)

    def centres(self, ijk: np.ndarray) -> np.ndarray:
        """(N, 3) float32 map coordinates of the centres of voxels (N, 3) ijk."""
        return ((ijk + 0.5) * self.voxel_m + self.origin_m).astype(np.float32)

    def flat(self, ijk: np.ndarray) -> np.ndarray:
        return np.ravel_multi_index(ijk.T, self.shape)


class OccupancyGrid:
    """Occupied / free / unknown voxels from every depth frame integrated so far."""

    def __init__(self, spec: GridSpec, ray_stride_px: int = 2) -> None:
        self.spec = spec
        self.ray_stride_px = ray_stride_px
        self.state = np.zeros(spec.shape, dtype=np.uint8)
        """(nx, ny, nz) uint8: bit FREE, bit OCCUPIED; 0 is unknown."""

    def integrate(self, depth_m: np.ndarray, k: CameraIntrinsics, T_map_camera: np.ndarray,
                  returns_map: np.ndarray | None = None) -> None:
        """Mark the returns of one z-depth frame occupied and the space before them free.

        ``returns_map``: the frame's back-projected returns, where the caller has them already
        (the mapper does, for S_t); computed here otherwise."""
        spec = self.spec
        flat_state = self.state.reshape(-1)
        # Free space first, from every ray_stride-th pixel (the voxels are several pixels wide
        # at range), sampled every half voxel up to one voxel short of the return.
        s = self.ray_stride_px
        sub = np.full_like(depth_m, np.nan)
        sub[::s, ::s] = depth_m[::s, ::s]
        hits = backproject(sub, k, T_map_camera).astype(np.float64)
        if len(hits):
            origin = T_map_camera[:3, 3]
            d = hits - origin
            length = np.linalg.norm(d, axis=1)
            unit = d / np.maximum(length, 1e-9)[:, None]
            step = 0.5 * spec.voxel_m
            t = np.arange(int(np.ceil(length.max() / step)) + 1) * step
            # A ray's samples are the t short of its return by more than a voxel, a prefix of
            # t: the (ray, t) pairs of np.nonzero(t[None, :] < (length - voxel_m)[:, None]), in
            # its order, without building that (rays, len(t)) mask.
            n = np.searchsorted(t, length - spec.voxel_m, side="left")
            rows = np.repeat(np.arange(len(n)), n)
            t_rows = t[np.arange(len(rows)) - np.repeat(np.cumsum(n) - n, n)]
            # The samples origin + unit * t and their voxels, one axis at a time (the same
            # arithmetic as spec.index, without (samples, 3) arrays).
            vi, vj, vk = (np.floor((origin[a] + unit[:, a][rows] * t_rows - spec.origin_m[a])
                                   / spec.voxel_m).astype(np.int64) for a in range(3))
            inside = spec.inside(vi, vj, vk)
            flat_state[self._flat(vi[inside], vj[inside], vk[inside])] |= FREE
        if returns_map is None:
            returns_map = backproject(depth_m, k, T_map_camera)
        ijk, inside = spec.index(returns_map)
        ijk = ijk[inside]
        flat_state[self._flat(ijk[:, 0], ijk[:, 1], ijk[:, 2])] |= OCCUPIED

    def _flat(self, i: np.ndarray, j: np.ndarray, k: np.ndarray) -> np.ndarray:
        """Flat C-order indices of voxels (i, j, k) in the grid (``spec.flat``, per axis)."""
        _, ny, nz = self.spec.shape
        return (i * ny + j) * nz + k

    def known(self, points_m: np.ndarray) -> np.ndarray:
        """(N,) bool: whether each point's voxel has been reached by depth (free or occupied).
        Points outside the grid count as unknown."""
        ijk, inside = self.spec.index(points_m)
        out = np.zeros(len(points_m), dtype=bool)
        out[inside] = self.state.reshape(-1)[self.spec.flat(ijk[inside])] != 0
        return out
