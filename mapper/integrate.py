"""Depth integration: back-projection and the voxel-downsampled observed surface S_t."""

from __future__ import annotations

import numpy as np

from rovergate.geometry import voxel_keys
from rovergate.types import CameraIntrinsics


def backproject(depth_m: np.ndarray, k: CameraIntrinsics, T_map_camera: np.ndarray) -> np.ndarray:
    """(N, 3) float32 map-frame points of the valid (finite) pixels of a z-depth image."""
    v, u = np.nonzero(np.isfinite(depth_m))
    z = depth_m[v, u].astype(np.float64)
    p_cam = np.stack([(u - k.cx) * z / k.fx, (v - k.cy) * z / k.fy, z], axis=1)
    return (p_cam @ T_map_camera[:3, :3].T + T_map_camera[:3, 3]).astype(np.float32)


#: The voxel index merges its recent keys into the main sorted run once they are this share of
#: it (:class:`VoxelSurface`): a frame then costs what it brings, not a sort of the whole map.
MERGE_SHARE = 0.25


class VoxelSurface:
    """The accumulated observed surface: one point per voxel, and in how many frames it was seen.

    A voxel keeps the first point that fell in it. New voxels are appended at the end, so
    ``points[:n]`` of an earlier step is a prefix of a later one (coverage uses that).

    The points live in buffers that grow by doubling, and the voxel keys in two sorted runs:
    the main one and the keys added since it was last merged, merged in once they are
    ``MERGE_SHARE`` of it. A frame's cost is then its own points' lookups plus an amortised
    share of the merges, not a copy and a sort of the whole surface (on a long traverse's
    million voxels that was some 100 ms a frame, and a restarted mapper paid it for every
    frame it replayed).
    """

    def __init__(self, voxel_m: float) -> None:
        self.voxel_m = voxel_m
        self._n = 0
        self._points = np.zeros((1024, 3), dtype=np.float32)
        self._views = np.zeros(1024, dtype=np.uint16)
        self._runs = [(np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64))] * 2

    @property
    def points(self) -> np.ndarray:
        """(N, 3) float32: one point per voxel, in the order the voxels were first seen."""
        return self._points[:self._n]

    @property
    def views(self) -> np.ndarray:
        """(N,) uint16: in how many frames each voxel was seen (saturating at 65,535)."""
        return self._views[:self._n]

    def __len__(self) -> int:
        return self._n

    def _lookup(self, keys: np.ndarray) -> np.ndarray:
        """(K,) int64: the index of each of the sorted, distinct ``keys``, -1 where new."""
        out = np.full(len(keys), -1, dtype=np.int64)
        for run_keys, run_index in self._runs:
            if len(run_keys):
                pos = np.minimum(np.searchsorted(run_keys, keys), len(run_keys) - 1)
                hit = run_keys[pos] == keys
                out[hit] = run_index[pos[hit]]
        return out

    def _grow(self, n: int) -> None:
        if n > len(self._points):
            size = max(n, 2 * len(self._points))
            for name in ("_points", "_views"):
                old = getattr(self, name)
                new = np.zeros((size, *old.shape[1:]), dtype=old.dtype)
                new[:self._n] = old[:self._n]
                setattr(self, name, new)

    def integrate(self, points: np.ndarray) -> int:
        """Add one frame's points; returns how many new voxels it created."""
        if len(points) == 0:
            return 0
        keys, first = np.unique(voxel_keys(points, self.voxel_m), return_index=True)
        index = self._lookup(keys)
        seen = index[index >= 0]
        self._views[seen] = np.minimum(self._views[seen].astype(np.int64) + 1, 65535)
        new = index < 0
        order = np.argsort(first[new], kind="stable")  # keep the frame's pixel order
        new_keys, new_first = keys[new][order], first[new][order]
        n_old, m = self._n, len(new_keys)
        self._grow(n_old + m)
        self._points[n_old:n_old + m] = points[new_first]
        self._views[n_old:n_old + m] = 1
        self._n = n_old + m
        (main_keys, main_index), (recent_keys, recent_index) = self._runs
        recent_keys = np.concatenate([recent_keys, new_keys])
        recent_index = np.concatenate([recent_index, np.arange(n_old, self._n)])
        o = np.argsort(recent_keys, kind="stable")
        recent = (recent_keys[o], recent_index[o])
        if len(recent[0]) > MERGE_SHARE * len(main_keys):
            all_keys = np.concatenate([main_keys, recent[0]])
            all_index = np.concatenate([main_index, recent[1]])
            o = np.argsort(all_keys, kind="stable")
            empty = np.zeros(0, dtype=np.int64)
            self._runs = [(all_keys[o], all_index[o]), (empty, empty)]
        else:
            self._runs = [(main_keys, main_index), recent]
        return m
