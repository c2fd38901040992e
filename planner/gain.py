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

A view sees a few per cent of the map (its frustum is narrow and 20 m deep), and the beam
search renders some 80 views a step, so :class:`GainField` keeps its primitives in blocks of
``BLOCK_M`` and projects only those of the blocks whose bounding sphere meets the view's
frustum (widened by a pixel): the same arithmetic on the same primitives as
:func:`visible_mask`, which the others could not pass, so the same result.
"""

from __future__ import annotations

import math

import numpy as np

from rovergate.geometry import frustum_halfspaces, halfspaces_in_map, pixels_of
from rovergate.types import CameraIntrinsics

#: Edge of the blocks that cull primitives outside a view (metres): big enough that a view's
#: blocks are few to test, small enough that they hug its frustum.
BLOCK_M = 2.0


def _erode(zbuf: np.ndarray) -> np.ndarray:
    """3 x 3 minimum over the last two axes of ``zbuf`` (..., H, W), edges repeated:
    ``scipy.ndimage.minimum_filter(..., size=3, mode="nearest")`` of each image (a minimum is
    exact in any order), without its set-up cost on images of a thousand pixels."""
    rows = zbuf.copy()
    np.minimum(rows[..., 1:, :], zbuf[..., :-1, :], out=rows[..., 1:, :])
    np.minimum(rows[..., :-1, :], zbuf[..., 1:, :], out=rows[..., :-1, :])
    out = rows.copy()
    np.minimum(out[..., 1:], rows[..., :-1], out=out[..., 1:])
    np.minimum(out[..., :-1], rows[..., 1:], out=out[..., :-1])
    return out


def _project(points_cam: np.ndarray, k: CameraIntrinsics, min_range_m: float,
             max_range_m: float, tolerance_m: float, views: np.ndarray | None = None,
             n_views: int = 1) -> np.ndarray:
    """(N,) bool: which of (N, 3) camera-frame points their camera sees (see
    :func:`visible_mask`). ``views``: (N,) index of each point's view among ``n_views``, each
    with its own z-buffer (None: one view)."""
    idx, v, u, zi = pixels_of(points_cam, k, min_range_m, max_range_m)
    visible = np.zeros(len(points_cam), dtype=bool)
    if len(idx) == 0:
        return visible
    pix = v * k.width + u
    if views is not None:
        pix += views[idx] * (k.width * k.height)
    zbuf = np.full(n_views * k.width * k.height, np.inf)
    np.minimum.at(zbuf, pix, zi)
    # Points are samples, not surfaces: close the one-pixel gaps between the samples of a
    # near surface so that it hides what is behind it.
    zbuf = _erode(zbuf.reshape(n_views, k.height, k.width)).ravel()
    visible[idx] = zi <= zbuf[pix] + tolerance_m
    return visible


def _to_camera(points_map: np.ndarray, T_map_camera: np.ndarray) -> np.ndarray:
    """(N, 3) float64 points in the camera frame of ``T_map_camera`` (optical: z forward)."""
    return (points_map - T_map_camera[:3, 3]) @ T_map_camera[:3, :3]


def visible_mask(points_map: np.ndarray, T_map_camera: np.ndarray, k: CameraIntrinsics,
                 min_range_m: float, max_range_m: float, tolerance_m: float) -> np.ndarray:
    """(N,) bool: the points a camera at ``T_map_camera`` sees, with occlusion."""
    return _project(_to_camera(np.asarray(points_map, dtype=np.float64), T_map_camera), k,
                    min_range_m, max_range_m, tolerance_m)


def _group(keys: np.ndarray, n_keys: int) -> tuple[np.ndarray, np.ndarray]:
    """``np.unique(keys, return_inverse=True, return_counts=True)[1:]`` of (N,) int64 keys in
    [0, n_keys): each key's rank among the distinct keys, and how many of each. Where the key
    range is small beside N (a map's voxels), ranks come from a running count over the range,
    which is cheaper than sorting the keys."""
    if n_keys > 8 * len(keys) + (1 << 20):
        _, inverse, count = np.unique(keys, return_inverse=True, return_counts=True)
        return inverse, count
    present = np.zeros(n_keys, dtype=bool)
    present[keys] = True
    inverse = (np.cumsum(present) - 1)[keys]
    return inverse, np.bincount(inverse)


class GainField:
    """One step's planner-facing map as weighted primitives, ready to render from any view.

    The primitives are held block by block (module docstring): ``centres`` and ``weight`` are
    in that order, and :meth:`visible` indexes them.
    """

    def __init__(self, points_map: np.ndarray, novel: np.ndarray, voxel_m: float,
                 k: CameraIntrinsics, min_range_m: float, max_range_m: float,
                 tolerance_m: float) -> None:
        self.k = k
        self.min_range_m, self.max_range_m, self.tolerance_m = min_range_m, max_range_m, tolerance_m
        p = np.asarray(points_map, dtype=np.float64)
        self._novel = np.asarray(novel, dtype=bool)
        if len(p) == 0:
            self.centres = np.zeros((0, 3))
            self.weight = np.zeros(0, dtype=np.int64)
            self._block_counts = np.zeros(0, dtype=np.int64)
            self._block_centres = np.zeros((0, 3))
            return
        ijk = np.floor(p / voxel_m).astype(np.int64)
        cols = [ijk[:, i] - ijk[:, i].min() for i in range(3)]  # (N, 3) reductions are slow
        span = [int(c.max()) + 1 for c in cols]
        keys = (cols[0] * span[1] + cols[1]) * span[2] + cols[2]
        inverse, count = _group(keys, span[0] * span[1] * span[2])
        centres = np.stack([np.bincount(inverse, weights=p[:, i]) for i in range(3)],
                           axis=1) / count[:, None]
        weight = np.bincount(inverse, weights=novel.astype(np.float64)).astype(np.int64)
        # Blocks: primitives sorted by block, each block's count and bounding-sphere centre.
        blk = np.floor(centres / BLOCK_M).astype(np.int64)
        bcols = [blk[:, i] - blk[:, i].min() for i in range(3)]
        bspan = [int(c.max()) + 1 for c in bcols]
        bkeys = (bcols[0] * bspan[1] + bcols[1]) * bspan[2] + bcols[2]
        order = np.argsort(bkeys, kind="stable")
        _, first, self._block_counts = np.unique(bkeys[order], return_index=True,
                                                 return_counts=True)
        self.centres = np.ascontiguousarray(centres[order])
        self.weight = weight[order]
        self._primitive = np.argsort(order, kind="stable")[inverse]  # each point's primitive
        self._block_centres = (blk[order[first]] + 0.5) * BLOCK_M
        # The view's frustum as half-spaces (rovergate.geometry.frustum_halfspaces): a block
        # passes while its bounding sphere (half its diagonal, and a millimetre for the
        # rounding of the test itself) reaches into every one of them.
        self._halfspaces = frustum_halfspaces(k, min_range_m, max_range_m)
        self._radius = BLOCK_M * math.sqrt(3.0) / 2 + 1e-3

    def weights(self, mask: np.ndarray) -> np.ndarray:
        """(P,) int64: how many of the points in (N,) bool ``mask`` each primitive holds (the
        ``weight`` a field built with ``novel = mask`` would have; evaluation weighs the gain
        of a subset of the points with it)."""
        if len(self.centres) == 0:
            return np.zeros(0, dtype=np.int64)
        return np.bincount(self._primitive, weights=mask.astype(np.float64),
                           minlength=len(self.centres)).astype(np.int64)

    def counted(self, visible: np.ndarray) -> np.ndarray:
        """(N,) bool over the field's points: the novel points of the ``visible`` primitives,
        the ones :meth:`gain` counts (``counted(v).sum() == gain(v)``)."""
        if len(self.centres) == 0:
            return np.zeros(len(self._novel), dtype=bool)
        hit = np.zeros(len(self.centres), dtype=bool)
        hit[visible] = True
        return self._novel & hit[self._primitive]

    def __len__(self) -> int:
        return len(self.centres)

    def _candidates(self, T_map_camera: np.ndarray) -> np.ndarray | None:
        """Sorted indices of the primitives in blocks the view may see (None: all of them)."""
        if self._halfspaces is None:
            return None
        m, off = halfspaces_in_map(T_map_camera, self._halfspaces)
        keep = (self._block_centres @ m - off).min(axis=1) >= -self._radius
        return np.flatnonzero(np.repeat(keep, self._block_counts))

    def visible(self, T_map_camera: np.ndarray) -> np.ndarray:
        """Indices of the primitives a camera at ``T_map_camera`` sees."""
        return self.visible_many([T_map_camera])[0]

    def visible_many(self, cameras: list[np.ndarray]) -> list[np.ndarray]:
        """:meth:`visible` of each of several views: the same arithmetic, in fewer and larger
        numpy calls (each view still has its own z-buffer)."""
        picks = [self._candidates(T) for T in cameras]
        picks = [np.arange(len(self)) if p is None else p for p in picks]
        if not picks:
            return []
        # Each view's points through its own matrix product, as visible_mask does for it.
        cam = np.concatenate([_to_camera(np.take(self.centres, p, axis=0), T)
                              for p, T in zip(picks, cameras, strict=True)])
        counts = [len(p) for p in picks]
        views = np.repeat(np.arange(len(cameras)), counts)
        seen = _project(cam, self.k, self.min_range_m, self.max_range_m, self.tolerance_m,
                        views, len(cameras))
        ends = np.cumsum(counts)
        return [p[seen[e - n:e]] for p, e, n in zip(picks, ends, counts, strict=True)]

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
