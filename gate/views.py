"""Seen-ness: one rule for every point the planner receives, in every condition.

A map point x has been *viewed* in a frame when the camera of that frame saw the place where it
lies: x is in front of the camera within the sensor's usable range, it projects inside the
image, and the frame's depth at its pixel is a valid return that ends no nearer than x minus
``tolerance_m``, or +Inf (nothing within range): the ray reached x. A nearer return means
something hid it; an invalid return (NaN) gives no evidence. Its views are the number of frames
so far that viewed it. The planner's gain counts a point as novel until it has
``observed_min_views`` views, whatever its source: observed surface, prediction or reference
point (MAGICIAN's gain, likewise, counts what the past camera poses saw). The tolerance
(``GateConfig.view_tolerance_m``) defaults to the planner's z-buffer tolerance, so a past view
"saw" a point when a candidate view at that pose would have counted it.

Counting is incremental and exact: the observed surface S_t and the reference O* only grow (or
stay), so their counts carry over and each step adds the newest frame; predicted and oracle
points are matched to last step's by their exact coordinates, and only points that are new are
counted against every past frame.
"""

from __future__ import annotations

import numpy as np

from rovergate.geometry import pixels_of
from rovergate.types import CameraIntrinsics


def row_keys(points: np.ndarray) -> np.ndarray:
    """1-D void view of (N, 3) float32 rows: exact keys for matching points across steps."""
    p = np.ascontiguousarray(points, dtype=np.float32)
    return p.view(np.dtype((np.void, 12))).ravel()


def extends(points: np.ndarray, n: int, last: np.ndarray | None) -> bool:
    """Whether ``points`` begins with an earlier set of ``n`` points that ended in ``last``
    (the observed surface only grows at its end; anything else starts the count over)."""
    return n <= len(points) and (n == 0 or np.array_equal(points[n - 1], last))


def pixels(points: np.ndarray, R: np.ndarray, t: np.ndarray, k: CameraIntrinsics,
           min_range_m: float, max_range_m: float
           ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Where a frame (map-to-optical rotation ``R``, translation ``t``) sees ``points``:
    ``(idx, v, u, z)`` of those in front of it within range that land on a pixel (the
    nearest), with their row, column and depth along the optical axis."""
    return pixels_of(np.asarray(points, dtype=np.float64) @ R.T + t, k, min_range_m,
                     max_range_m)


class _Frame:
    __slots__ = ("R", "t", "k", "depth")

    def __init__(self, T_map_camera: np.ndarray, k: CameraIntrinsics, depth: np.ndarray) -> None:
        self.R = T_map_camera[:3, :3].T
        self.t = -self.R @ T_map_camera[:3, 3]
        self.k = k
        self.depth = np.asarray(depth, dtype=np.float32)


class ViewCounter:
    """The frames so far, and the views of every planner-facing point (module docstring)."""

    def __init__(self, min_range_m: float, max_range_m: float, tolerance_m: float) -> None:
        self.min_range_m, self.max_range_m, self.tolerance_m = min_range_m, max_range_m, tolerance_m
        self.frames: list[_Frame] = []
        # Per part: counts through the frames at the last call, and the keys they belong to.
        self._grown: dict[str, tuple[int, np.ndarray, np.ndarray]] = {}
        self._keyed: dict[str, tuple[int, np.ndarray, np.ndarray]] = {}

    def add_frame(self, T_map_camera: np.ndarray, k: CameraIntrinsics, depth: np.ndarray
                  ) -> None:
        self.frames.append(_Frame(T_map_camera, k, depth))

    def count(self, points: np.ndarray, first: int = 0) -> np.ndarray:
        """(N,) int64: frames ``first``.. that viewed each point (the rule, from scratch)."""
        out = np.zeros(len(points), dtype=np.int64)
        if len(points) == 0:
            return out
        p = np.asarray(points, dtype=np.float64)
        for frame in self.frames[first:]:
            idx, v, u, z = pixels(p, frame.R, frame.t, frame.k, self.min_range_m,
                                  self.max_range_m)
            seen = frame.depth[v, u] >= z - self.tolerance_m  # NaN (no return): False
            out[idx[seen]] += 1
        return out

    def views_grown(self, part: str, points: np.ndarray) -> np.ndarray:
        """Views of a point set that only grows at its end (S_t, O*): the points it had at the
        last call carry their counts and add the frames since; new points count them all."""
        n_frames = len(self.frames)
        done, counts, last = self._grown.get(part, (0, np.zeros(0, np.int64),
                                                    np.zeros((0, 3), np.float32)))
        n_old = len(counts)
        if not extends(points, n_old, last):
            done, counts, n_old = 0, np.zeros(0, np.int64), 0  # not an extension: start over
        out = np.empty(len(points), dtype=np.int64)
        out[:n_old] = counts + self.count(points[:n_old], first=done)
        out[n_old:] = self.count(points[n_old:])
        self._grown[part] = (n_frames, out,
                             np.array(points[-1] if len(points) else np.zeros(3), np.float32))
        return out

    def views_keyed(self, part: str, points: np.ndarray) -> np.ndarray:
        """Views of a point set that changes every step (predictions, oracle points): points
        seen at the last call (same coordinates) add the frames since; others count them all."""
        n_frames = len(self.frames)
        done, keys, counts = self._keyed.get(part, (0, row_keys(np.zeros((0, 3))),
                                                    np.zeros(0, np.int64)))
        rows = row_keys(points)
        out = np.empty(len(points), dtype=np.int64)
        hit = np.zeros(len(points), dtype=bool)
        if len(keys) and len(rows):
            i = np.minimum(np.searchsorted(keys, rows), len(keys) - 1)
            hit = keys[i] == rows
            out[hit] = counts[i[hit]] + self.count(points[hit], first=done)
        out[~hit] = self.count(points[~hit])
        order = np.argsort(rows, kind="stable")
        self._keyed[part] = (n_frames, rows[order], out[order])
        return out


def as_views(counts: np.ndarray) -> np.ndarray:
    """Counts as the map's uint16 ``views`` field (saturating)."""
    return np.minimum(counts, np.iinfo(np.uint16).max).astype(np.uint16)
