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


class VoxelSurface:
    """The accumulated observed surface: one point per voxel, and in how many frames it was seen.

    A voxel keeps the first point that fell in it. New voxels are appended at the end, so
    ``points[:n]`` of an earlier step is a prefix of a later one (coverage uses that).
    """

    def __init__(self, voxel_m: float) -> None:
        self.voxel_m = voxel_m
        self.points = np.zeros((0, 3), dtype=np.float32)
        self.views = np.zeros(0, dtype=np.uint16)
        self._sorted_keys = np.zeros(0, dtype=np.int64)
        self._sorted_index = np.zeros(0, dtype=np.int64)

    def __len__(self) -> int:
        return len(self.points)

    def integrate(self, points: np.ndarray) -> int:
        """Add one frame's points; returns how many new voxels it created."""
        if len(points) == 0:
            return 0
        keys, first = np.unique(voxel_keys(points, self.voxel_m), return_index=True)
        if len(self._sorted_keys):
            pos = np.minimum(np.searchsorted(self._sorted_keys, keys), len(self._sorted_keys) - 1)
            known = self._sorted_keys[pos] == keys
        else:
            pos, known = np.zeros(len(keys), dtype=np.int64), np.zeros(len(keys), dtype=bool)
        seen = self._sorted_index[pos[known]]
        self.views[seen] = np.minimum(self.views[seen].astype(np.int64) + 1, 65535)
        new = ~known
        order = np.argsort(first[new], kind="stable")  # keep the frame's pixel order
        new_keys, new_first = keys[new][order], first[new][order]
        n_old = len(self.points)
        self.points = np.concatenate([self.points, points[new_first]])
        self.views = np.concatenate([self.views, np.ones(len(new_keys), dtype=np.uint16)])
        all_keys = np.concatenate([self._sorted_keys, new_keys])
        all_index = np.concatenate([self._sorted_index, np.arange(n_old, len(self.points))])
        o = np.argsort(all_keys, kind="stable")
        self._sorted_keys, self._sorted_index = all_keys[o], all_index[o]
        return len(new_keys)
