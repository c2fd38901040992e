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

Counting is also local: a frame can only view what lies in its frustum, 20 m deep and a few
tens of degrees wide, so points are kept in blocks of ``BLOCK_M`` and a frame projects only
the points of the blocks whose bounding sphere meets its frustum (:class:`Frustums`; the test
only ever keeps too much, so the counts are the same to the bit). A step's cost then follows
what is near the camera and what is new, not the whole map: the observed surface's blocks
are indexed as it grows (:class:`Blocks`), and a new point is tested against the frames whose
frustums reach its block, not against every frame of the mission.
"""

from __future__ import annotations

import numpy as np

from rovergate.geometry import (
    frustum_halfspaces,
    halfspaces_in_map,
    pixels_of,
    voxel_centres,
    voxel_keys,
)
from rovergate.types import CameraIntrinsics

#: Edge of the blocks that cull points outside a frame (metres): the gain's blocks are 2 m;
#: a frame meets a few hundred of these, and a mission's map some thousands.
BLOCK_M = 4.0
_BLOCK_RADIUS = BLOCK_M * np.sqrt(3.0) / 2 + 1e-3  # half a diagonal and a millimetre


def block_groups(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The blocks that hold (N, 3) points: ``(centres (B, 3), block (N,))``, each point's
    index into ``centres``."""
    keys, block = np.unique(voxel_keys(np.asarray(points), BLOCK_M), return_inverse=True)
    return voxel_centres(keys, BLOCK_M), block.ravel()


class Frustums:
    """The frustums of the frames so far, to tell which blocks each may see.

    Every frame's frustum is held as six half-spaces in the map frame
    (:func:`rovergate.geometry.frustum_halfspaces`). With a minimum range of zero the side
    planes bound nothing and every block passes."""

    def __init__(self, min_range_m: float, max_range_m: float) -> None:
        self.min_range_m, self.max_range_m = min_range_m, max_range_m
        self._m = np.zeros((0, 3, 6))
        self._off = np.zeros((0, 6))
        self._n = 0
        self.cull = min_range_m > 0

    def __len__(self) -> int:
        return self._n

    def add(self, T_map_camera: np.ndarray, k: CameraIntrinsics) -> None:
        if not self.cull:
            self._n += 1
            return
        halfspaces = frustum_halfspaces(k, self.min_range_m, self.max_range_m)
        assert halfspaces is not None
        m, off = halfspaces_in_map(T_map_camera, halfspaces)
        if self._n == len(self._m):  # grow by doubling: a frame's add stays O(1)
            grown = max(16, 2 * self._n)
            self._m = np.concatenate([self._m, np.zeros((grown - self._n, 3, 6))])
            self._off = np.concatenate([self._off, np.zeros((grown - self._n, 6))])
        self._m[self._n], self._off[self._n] = m, off
        self._n += 1

    def meets(self, centres: np.ndarray, first: int = 0, last: int | None = None
              ) -> np.ndarray:
        """(F, B) bool: which of the blocks at ``centres`` (B, 3) each frame ``first`` to
        ``last`` (exclusive; None: all) may see."""
        last = self._n if last is None else last
        if not self.cull:
            return np.ones((last - first, len(centres)), dtype=bool)
        d = np.einsum("bi,fij->fbj", centres, self._m[first:last]) - self._off[first:last, None]
        return d.min(axis=2) >= -_BLOCK_RADIUS


class Blocks:
    """The points of a set that grows at its end, by block (:data:`BLOCK_M`): which of them
    lie in a set of blocks, at a cost that follows how many they hold, not the whole set."""

    def __init__(self) -> None:
        self.n = 0
        self._slot: dict[int, int] = {}        # block key -> its slot
        self._members: list[list[np.ndarray]] = []  # per slot: index arrays, in order
        self.centres = np.zeros((0, 3))

    def extend(self, points: np.ndarray) -> None:
        """Index ``points``, the set's next ``len(points)`` points."""
        if len(points) == 0:
            return
        keys = voxel_keys(np.asarray(points), BLOCK_M)
        order = np.argsort(keys, kind="stable")
        uniq, first = np.unique(keys[order], return_index=True)
        new = [int(u) for u in uniq if int(u) not in self._slot]
        for key in new:
            self._slot[key] = len(self._members)
            self._members.append([])
        if new:
            self.centres = np.concatenate([self.centres,
                                           voxel_centres(np.array(new, np.int64), BLOCK_M)])
        for key, part in zip(uniq.tolist(), np.split(order + self.n, first[1:]), strict=True):
            self._members[self._slot[key]].append(part)
        self.n += len(points)

    def members(self, blocks: np.ndarray) -> np.ndarray:
        """Indices of the points in the blocks of (B,) bool ``blocks``."""
        parts = []
        for slot in np.flatnonzero(blocks):
            chunks = self._members[slot]
            if len(chunks) > 1:  # keep each block one array
                chunks[:] = [np.concatenate(chunks)]
            parts.append(chunks[0])
        return np.concatenate(parts) if parts else np.zeros(0, np.int64)


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
        self.frustums = Frustums(min_range_m, max_range_m)
        # Per part: counts through the frames at the last call, the last point (to tell an
        # extension) and the points' blocks; or the keys the counts belong to.
        self._grown: dict[str, tuple[int, np.ndarray, np.ndarray, Blocks]] = {}
        self._keyed: dict[str, tuple[int, np.ndarray, np.ndarray]] = {}

    def add_frame(self, T_map_camera: np.ndarray, k: CameraIntrinsics, depth: np.ndarray
                  ) -> None:
        self.frames.append(_Frame(T_map_camera, k, depth))
        self.frustums.add(T_map_camera, k)

    def _viewed(self, frame: _Frame, points: np.ndarray, idx: np.ndarray, out: np.ndarray
                ) -> None:
        """Add frame's view to ``out`` at those of ``points[idx]`` it viewed."""
        if len(idx) == 0:
            return
        i, v, u, z = pixels(points[idx], frame.R, frame.t, frame.k, self.min_range_m,
                            self.max_range_m)
        seen = frame.depth[v, u] >= z - self.tolerance_m  # NaN (no return): False
        out[idx[i[seen]]] += 1

    def count(self, points: np.ndarray, first: int = 0) -> np.ndarray:
        """(N,) int64: frames ``first``.. that viewed each point (the rule, from scratch; each
        frame projects only the points of the blocks its frustum meets)."""
        out = np.zeros(len(points), dtype=np.int64)
        if len(points) == 0 or first >= len(self.frames):
            return out
        centres, block = block_groups(points)
        meets = self.frustums.meets(centres, first)
        for f in np.flatnonzero(meets.any(axis=1)):
            self._viewed(self.frames[first + f], points, np.flatnonzero(meets[f][block]), out)
        return out

    def views_grown(self, part: str, points: np.ndarray) -> np.ndarray:
        """Views of a point set that only grows at its end (S_t, O*): the points it had at the
        last call carry their counts and add the frames since (each projecting the points of
        the blocks it meets, from the set's block index); new points count them all."""
        n_frames = len(self.frames)
        state = self._grown.get(part)
        if state is None or not extends(points, len(state[1]), state[2]):
            state = (0, np.zeros(0, np.int64), np.zeros(3, np.float32), Blocks())
        done, counts, _, blocks = state  # not an extension: start over
        n_old = len(counts)
        out = np.empty(len(points), dtype=np.int64)
        out[:n_old] = counts
        if n_old:
            for f in range(done, n_frames):
                meets = self.frustums.meets(blocks.centres, f, f + 1)[0]
                self._viewed(self.frames[f], points, blocks.members(meets), out)
        out[n_old:] = self.count(points[n_old:])
        blocks.extend(points[n_old:])
        self._grown[part] = (n_frames, out,
                             np.array(points[-1] if len(points) else np.zeros(3), np.float32),
                             blocks)
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
