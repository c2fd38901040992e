"""Collision checking of the rover body against the planner-facing occupancy, with FCL.

The map is a point set, so the ground itself is made of points. The model first estimates the
ground: the lowest map point in each ``ground_cell_m`` cell, and the plane fitted to those of
the 3 x 3 cells around each. A map point is an obstacle when it stands between the body's
clearance and its top above its local plane (overhangs higher than the body are passed under;
pebbles lower than the clearance are driven over). Each obstacle point becomes a small box in
an FCL broad-phase manager at its height above the plane; the rover is the box of its body in
the same plane-relative heights, as its body tilts with the ground.

The rover's limits are checked on the same estimate: the plane fitted to the lowest map points
of the cells around a pose must be no steeper than the slope limit, and none of them farther
from it than the step limit (cells without points are unknown and pass here: the rover's
traversability layer, :mod:`planner.traversability`, refuses unknown ground). The flyer's
model (:class:`FlyerCollisionModel`) keeps its sphere clear of every map point and between its
altitude limits over the estimated ground, and, given the known free space
(:mod:`planner.freespace`), its centre out of the unknown.

Everything reads the same planner-facing map as the gain: a hallucinated point both attracts
the platform and blocks its way, as in the paper.
"""

from __future__ import annotations

import math
import threading
import weakref

import fcl
import numpy as np
from scipy.spatial import cKDTree

from planner.freespace import FreeSpace
from rovergate.config import FlyerConfig, RoverConfig
from rovergate.spatial import kdtree


def _box_minimum(grid: np.ndarray, size: int) -> np.ndarray:
    """The minimum over each ``size`` x ``size`` box, the edges repeated: what
    ``scipy.ndimage.minimum_filter(grid, size, mode="nearest")`` gives (a minimum is exact, so
    to the bit), as two passes of sliding windows. Importing scipy.ndimage cost every planner
    process 0.25 s of its start-up."""
    r = size // 2
    padded = np.pad(grid, r, mode="edge")
    view = np.lib.stride_tricks.sliding_window_view
    return view(view(padded, size, axis=0).min(axis=-1), size, axis=1).min(axis=-1)


_OFFSETS = [(di, dj) for di in (-1, 0, 1) for dj in (-1, 0, 1)]

BODY_MARGIN_M = 0.1
"""The rover's body as the planner checks it is this much larger on every side (and points
this much under its clearance or over its top are obstacles)."""


#: How much narrower (on every side) than the true body an escape is checked: about half the
#: map's voxel, the error of a voxel-snapped surface sample. A rover that touched a rock
#: stands where the simulator's bumper stopped it, a few centimetres from the true surface,
#: and the rock's samples may lie closer than that to its body.
ESCAPE_SHRINK_M = 0.08


class _BoxPool:
    """FCL boxes of one edge, kept and moved instead of made anew each step.

    python-fcl (0.7) never frees a ``CollisionObject`` it made: about 38 bytes each, and a
    rover mission makes one per obstacle point per step (some 250,000 in 100 steps), which a
    study worker running hundreds of missions kept for good. A model takes its boxes from
    here and gives them back when it is collected (``weakref.finalize``); a box taken is
    exclusively the taker's until then, and is moved (``setTranslation``) before use. The pool
    is as large as the most boxes ever held at once."""

    def __init__(self, edge: float) -> None:
        self.edge = edge
        self._geometry = fcl.Box(edge, edge, edge)
        self._free: list[fcl.CollisionObject] = []
        self._lock = threading.Lock()
        self.made = 0

    def take(self, points: np.ndarray) -> list[fcl.CollisionObject]:
        """Boxes at ``points`` ((N, 3) float64)."""
        with self._lock:
            n = len(points)
            reused = self._free[len(self._free) - n:] if n <= len(self._free) else self._free
            self._free = self._free[:len(self._free) - len(reused)]
            objects = list(reused)
            for _ in range(n - len(objects)):
                objects.append(fcl.CollisionObject(self._geometry))
                self.made += 1
        for o, p in zip(objects, points, strict=True):
            o.setTranslation(p)
        return objects

    def give(self, objects: list[fcl.CollisionObject]) -> None:
        with self._lock:
            self._free.extend(objects)


_POOLS: dict[float, _BoxPool] = {}


def box_pool(edge: float) -> _BoxPool:
    """The process's pool of boxes of ``edge`` metres."""
    pool = _POOLS.get(edge)
    if pool is None:
        pool = _POOLS.setdefault(edge, _BoxPool(edge))
    return pool


#: The ground grid reaches this far beyond the box it is given on every side.
GRID_MARGIN_M = 5.0


class OccupancyCollisionModel:
    """FCL model of one step's planner-facing occupancy."""

    def __init__(self, points_map: np.ndarray, rover: RoverConfig, bounds_m: tuple[float, ...],
                 ground_cell_m: float, obstacle_voxel_m: float, fallback_ground_z: float,
                 predicted: np.ndarray | None = None, contacts: np.ndarray | None = None,
                 ground_ref=None) -> None:
        """``ground_ref``: the rover's measured ground, a callable (N, 2) positions ->
        (known, height) (:meth:`planner.traversability.TerrainMap.ground_at`): where it knows
        the ground, a map point's height is taken over it rather than over the map's own
        estimate (the lowest points of 0.5 m cells, which sinks below a crest and makes the
        ground of a crater's rim an obstacle). ``predicted``: (N,) bool, the points that are
        predictions, not measurements. A cell's ground comes from its measured points when it
        has any: a prediction's height is uncertain by its voxel, and one low predicted point
        would sink the ground estimate under everything measured around it; then from
        ``ground_ref`` where it knows the cell's centre; then from its predictions.
        ``contacts``: points where the rover touched the scene: obstacles whatever their
        height (a bumper's reading, not ground)."""
        self.rover = rover
        self._ground_ref = ground_ref
        self._contacts = np.zeros((0, 3)) if contacts is None else np.asarray(contacts)
        self.cell = ground_cell_m
        self.fallback_ground_z = fallback_ground_z
        xmin, ymin, _, xmax, ymax, _ = bounds_m
        margin = GRID_MARGIN_M
        self.origin = np.array([xmin - margin, ymin - margin])
        self._ox, self._oy = float(self.origin[0]), float(self.origin[1])
        self.shape = (int(np.ceil((ymax - ymin + 2 * margin) / ground_cell_m)) + 1,
                      int(np.ceil((xmax - xmin + 2 * margin) / ground_cell_m)) + 1)
        grid = np.full(self.shape, np.inf)
        p = np.asarray(points_map)
        # Cells as _cells gives them, a column at a time, and as flat indices: ufunc.at on a
        # flat index into a 1-D view takes its fast path (eight times faster than on a tuple
        # of index arrays); the minimum of each cell is the same whatever the order.
        row = np.floor((p[:, 1].astype(np.float64) - self._oy) / self.cell).astype(np.int64)
        col = np.floor((p[:, 0].astype(np.float64) - self._ox) / self.cell).astype(np.int64)
        inside = (row >= 0) & (row < self.shape[0]) & (col >= 0) & (col < self.shape[1])
        flat = row * self.shape[1] + col
        z = p[:, 2].astype(np.float64)
        measured = inside if predicted is None else inside & ~predicted
        np.minimum.at(grid.reshape(-1), flat[measured], z[measured])
        if predicted is not None:
            guess = np.full(self.shape, np.inf)
            only = inside & predicted
            np.minimum.at(guess.reshape(-1), flat[only], z[only])
            if ground_ref is not None:
                # A cell whose ground only predictions give, where the rover measured the
                # ground: the measurement (the camera's rays stopped on that surface, so no
                # prediction under it can be ground; one above it is still judged as an
                # obstacle against it, _map_obstacles).
                ii, jj = np.nonzero(np.isfinite(guess) & ~np.isfinite(grid))
                if len(ii):
                    centres = np.c_[self._ox + (jj + 0.5) * self.cell,
                                    self._oy + (ii + 0.5) * self.cell]
                    known, zref = ground_ref(centres)
                    guess[ii[known], jj[known]] = zref[known]
            grid = np.where(np.isfinite(grid), grid, guess)
        half_diag = np.hypot(rover.length_m, rover.width_m) / 2
        size = 2 * int(np.ceil(half_diag / ground_cell_m)) + 1
        self.raw_ground = grid
        self.ground = _box_minimum(grid, size)
        self._terrain: tuple[np.ndarray, np.ndarray] | None = None
        self._plane: np.ndarray | None = None
        self._inside = (p[inside], np.c_[row[inside], col[inside]])
        self._obstacles: np.ndarray | None = None
        self._map_obstacle_cache: tuple[np.ndarray, np.ndarray] | None = None
        self._edge = obstacle_voxel_m
        self._manager: fcl.DynamicAABBTreeCollisionManager | None = None  # built on first use
        # The body, widened by BODY_MARGIN_M on every side, above and below too: the map
        # samples surfaces, so a corner must not slip between two samples of a rock, and a
        # rock whose samples read a little under the clearance may still graze the body.
        body_h = rover.body_top_m - rover.clearance_m
        self._body = fcl.CollisionObject(fcl.Box(rover.length_m + 2 * BODY_MARGIN_M,
                                                 rover.width_m + 2 * BODY_MARGIN_M,
                                                 body_h + 2 * BODY_MARGIN_M))
        self._core = fcl.CollisionObject(fcl.Box(rover.length_m, rover.width_m, body_h))
        # An escape's check: the true body less the map's own error on every side.
        self._escape = fcl.CollisionObject(fcl.Box(rover.length_m - 2 * ESCAPE_SHRINK_M,
                                                   rover.width_m - 2 * ESCAPE_SHRINK_M,
                                                   body_h))
        self._body_dz = rover.clearance_m + body_h / 2
        self.checks = 0

    @property
    def obstacle_points(self) -> np.ndarray:
        """(M, 3) the obstacle points as (x, y, height above their local ground plane).

        Obstacles stand out of the local ground plane (fitted to the lowest points of the
        cells around theirs), not out of the lowest ground nearby: on a slope, the lowest
        ground a body length away lies far below, and the slope itself would be an obstacle.
        The body is checked in the same plane-relative heights (the terrain "flattened"), as
        the rover's body tilts with the ground it stands on. Computed on first use (the
        flyer's checks never need it)."""
        if self._obstacles is None:
            pts, h = self._map_obstacles()
            self._obstacles = np.c_[pts[:, :2], h]
            if len(self._contacts):  # in the middle of the body's band
                mid = (self.rover.clearance_m + self.rover.body_top_m) / 2
                self._obstacles = np.vstack([self._obstacles, np.c_[
                    self._contacts[:, :2], np.full(len(self._contacts), mid)]])
        return self._obstacles

    @property
    def obstacle_xyz(self) -> np.ndarray:
        """(M', 3) the map's obstacle points as the map has them (x, y, z); contacts aside."""
        return self._map_obstacles()[0]

    def _map_obstacles(self) -> tuple[np.ndarray, np.ndarray]:
        """The map points standing in the body's height band over their local ground plane,
        and those heights."""
        if self._map_obstacle_cache is None:
            pts, ij = self._inside
            h = pts[:, 2] - self._ground_plane(pts[:, :2], ij)
            if self._ground_ref is not None and len(pts):
                known, z = self._ground_ref(pts[:, :2].astype(np.float64))
                h = np.where(known, pts[:, 2] - z, h)
            keep = ((h > self.rover.clearance_m - BODY_MARGIN_M)
                    & (h < self.rover.body_top_m + BODY_MARGIN_M))
            self._map_obstacle_cache = (pts[keep], h[keep])
        return self._map_obstacle_cache

    def _build_manager(self) -> fcl.DynamicAABBTreeCollisionManager:
        """The FCL broad phase over the obstacle points (built only when the body is checked:
        the flyer's sphere never is)."""
        pool = box_pool(self._edge)
        self._objects = pool.take(self.obstacle_points.astype(np.float64))
        # Back to the pool once this model (and with it its manager) is collected.
        weakref.finalize(self, pool.give, self._objects)
        manager = fcl.DynamicAABBTreeCollisionManager()
        manager.registerObjects(self._objects)
        manager.setup()
        return manager

    def _cells(self, xy: np.ndarray) -> np.ndarray:
        ij = np.floor((xy - self.origin) / self.cell).astype(np.int64)
        return ij[:, ::-1]  # (row = y, col = x)

    def _cell(self, x: float, y: float) -> tuple[int, int]:
        """(row, col) of one point: the scalar fast path of :meth:`_cells` (OMPL calls it
        thousands of times a step)."""
        return (math.floor((y - self._oy) / self.cell), math.floor((x - self._ox) / self.cell))

    def ground_z(self, x: float, y: float) -> float:
        """Estimated ground height under (x, y); the fallback where the map has no points."""
        i, j = self._cell(x, y)
        if 0 <= i < self.shape[0] and 0 <= j < self.shape[1]:
            g = float(self.ground[i, j])
            if math.isfinite(g):
                return g
        return self.fallback_ground_z

    def ground_z_many(self, xy: np.ndarray) -> np.ndarray:
        """(N,) estimated ground height under each of (N, 2) positions (see :meth:`ground_z`)."""
        ij = self._cells(np.asarray(xy, dtype=np.float64))
        ok = ((ij[:, 0] >= 0) & (ij[:, 0] < self.shape[0]) & (ij[:, 1] >= 0)
              & (ij[:, 1] < self.shape[1]))
        g = np.full(len(ij), self.fallback_ground_z)
        g[ok] = self.ground[ij[ok, 0], ij[ok, 1]]
        return np.where(np.isfinite(g), g, self.fallback_ground_z)

    def _terrain_grid(self) -> tuple[np.ndarray, np.ndarray]:
        """Per cell: whether the ground around it is known, and whether it is within limits.

        A plane is fitted by least squares to the known cells of the 3 x 3 window around each
        cell (a square of 1.5 m: the body in any heading); the cell fails when the plane is
        steeper than the slope limit or a known cell departs from it by more than the step
        limit. Computed once per map, for every cell at once.
        """
        raw = self.raw_ground
        K = np.isfinite(raw).astype(np.float64)
        Z = np.where(K > 0, raw, 0.0)
        known, coef = self._fit(K, Z)
        ok = np.hypot(coef[..., 1], coef[..., 2]) <= np.tan(np.radians(self.rover.slope_limit_deg))
        above = np.zeros(raw.shape, dtype=bool)  # cells standing out of some window's plane
        for _, _, k, z, plane in self._residuals(K, Z, coef):
            ok &= ~k | (np.abs(z - plane) <= self.rover.step_limit_m)
        # The ground plane obstacles are measured from: refitted without the cells that stand
        # out of the first fit by more than half the step limit (a cell whose lowest point is
        # a rock's top would otherwise lift the plane, and hide the rock).
        for di, dj, k, z, plane in self._residuals(K, Z, coef):
            out = k & (z - plane > self.rover.step_limit_m / 2)
            h, w = raw.shape
            above[max(di, 0):h + min(di, 0), max(dj, 0):w + min(dj, 0)] |= \
                out[max(-di, 0):h - max(di, 0), max(-dj, 0):w - max(dj, 0)]
        known_r, coef_r = self._fit(K * ~above, Z)
        # Where too few cells are left for the refit, the first fit's plane stands.
        self._plane = np.where(known_r[..., None], coef_r, coef)
        self._plane_known = known
        return known, ok | ~known

    def _fit(self, K: np.ndarray, Z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Least-squares planes over the 3 x 3 windows: (known, coef), coef (h, w, 3) the
        height at the cell centre and the slopes in x and y; known: at least 4 cells."""
        Kp, Zp = np.pad(K, 1), np.pad(Z, 1)
        h, w = K.shape
        M = np.zeros((h, w, 3, 3))
        r = np.zeros((h, w, 3))
        n = np.zeros((h, w))
        for di, dj in _OFFSETS:
            k = Kp[1 + di:1 + di + h, 1 + dj:1 + dj + w]
            z = Zp[1 + di:1 + di + h, 1 + dj:1 + dj + w]
            f = np.array([1.0, dj * self.cell, di * self.cell])
            M += k[..., None, None] * np.outer(f, f)
            r += (k * z)[..., None] * f
            n += k
        known = n >= 4
        M[~known] = np.eye(3)
        r[~known] = 0.0
        return known, np.linalg.solve(M, r[..., None])[..., 0]

    def _residuals(self, K: np.ndarray, Z: np.ndarray, coef: np.ndarray):
        """For each window offset: (di, dj, known there, lowest height there, plane there)."""
        Kp, Zp = np.pad(K, 1), np.pad(Z, 1)
        h, w = K.shape
        for di, dj in _OFFSETS:
            k = Kp[1 + di:1 + di + h, 1 + dj:1 + dj + w] > 0
            z = Zp[1 + di:1 + di + h, 1 + dj:1 + dj + w]
            plane = coef[..., 0] + coef[..., 1] * dj * self.cell + coef[..., 2] * di * self.cell
            yield di, dj, k, z, plane

    def _ground_plane(self, xy: np.ndarray, ij: np.ndarray) -> np.ndarray:
        """(N,) height of the local ground plane under each of (N, 2) positions in cells ``ij``
        (the plane :meth:`_terrain_grid` fits around the cell; where too little ground is
        known for a plane, the lowest ground nearby)."""
        if self._plane is None:
            self._terrain = self._terrain_grid()
        coef, known = self._plane, self._plane_known
        i, j = ij[:, 0], ij[:, 1]
        dx = xy[:, 0] - (self._ox + (j + 0.5) * self.cell)
        dy = xy[:, 1] - (self._oy + (i + 0.5) * self.cell)
        plane = coef[i, j, 0] + coef[i, j, 1] * dx + coef[i, j, 2] * dy
        return np.where(known[i, j], plane, self.ground[i, j])

    def traversable(self, x: float, y: float, yaw: float) -> bool:
        """Whether the estimated ground at (x, y) is within the slope and step limits (where
        the map holds no ground it passes: the rover's own traversability layer,
        :mod:`planner.traversability`, refuses unknown ground)."""
        if self._terrain is None:
            self._terrain = self._terrain_grid()
        _, ok = self._terrain
        i, j = self._cell(x, y)
        if not (0 <= i < self.shape[0] and 0 <= j < self.shape[1]):
            return True
        return bool(ok[i, j])

    def is_free(self, x: float, y: float, yaw: float, margin: bool | str = True) -> bool:
        """Whether the body at (x, y, yaw) on the estimated ground touches no obstacle point
        and stands within the rover's slope and step limits (``margin``: the body widened by
        ``BODY_MARGIN_M``; False, the true body; "escape", the true body narrowed by
        ``ESCAPE_SHRINK_M``, the check of an escape from a spot the map blocks)."""
        self.checks += 1
        if not self.traversable(x, y, yaw):
            return False
        if len(self.obstacle_points) == 0:
            return True
        if self._manager is None:
            self._manager = self._build_manager()
        c, s = np.cos(yaw), np.sin(yaw)
        R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        body = self._escape if margin == "escape" else self._body if margin else self._core
        body.setTransform(fcl.Transform(R, [x, y, self._body_dz]))  # plane-relative
        data = fcl.CollisionData(request=fcl.CollisionRequest())
        self._manager.collide(body, data, fcl.defaultCollisionCallback)
        return not data.result.is_collision


#: Half the side of the square, around the flyer's first sphere check of a step, whose points
#: its first k-d tree holds (metres). The beam search's checks lie within three motions of
#: ``max_step_m`` (3 m) of the current position, and its first check within one.
NEAR_HALF_M = 14.0


class FlyerCollisionModel:
    """The flyer's check on one step's planner-facing occupancy: a sphere among points.

    The points are indexed when first checked, and in two k-d trees: the first check fixes a
    square of ``NEAR_HALF_M`` around it, whose points one tree holds; a check whose sphere
    lies inside that square is answered by it (every point that could touch the sphere is in
    the square), any other by a tree of all the points, built the first time one is needed (an
    RRT search that wanders). Both give the distance to the same nearest point, so every
    answer is that of one tree of all the points; a step's search mostly stays near where it
    starts, and the near tree holds half the map or less.
    """

    def __init__(self, points_map: np.ndarray, flyer: FlyerConfig, ground: OccupancyCollisionModel,
                 margin_m: float = 0.2, free: FreeSpace | None = None) -> None:
        """``free``: the known free space; with it, the sphere's centre must lie in it."""
        self.cfg = flyer
        self.ground = ground
        self.free = free
        self.reach = flyer.radius_m + margin_m
        self._points = np.asarray(points_map)
        self._near: tuple[cKDTree | None, float, float] | None = None  # tree, centre x, y
        self._all: cKDTree | None = None
        self.checks = 0

    def _tree(self, xy: np.ndarray) -> cKDTree | None:
        """The tree that answers checks of sphere centres at (N, 2) ``xy`` (None: no points
        near them)."""
        if self._near is None:
            cx, cy = float(xy[0, 0]), float(xy[0, 1])
            p = self._points
            near = ((np.abs(p[:, 0].astype(np.float64) - cx) <= NEAR_HALF_M)
                    & (np.abs(p[:, 1].astype(np.float64) - cy) <= NEAR_HALF_M))
            self._near = (kdtree(p[near]) if near.any() else None, cx, cy)
        tree, cx, cy = self._near
        inner = NEAR_HALF_M - self.reach - 1e-6
        if (np.abs(xy[:, 0] - cx) <= inner).all() and (np.abs(xy[:, 1] - cy) <= inner).all():
            return tree
        if self._all is None:
            self._all = kdtree(self._points)
        return self._all

    def altitude_band(self, x: float, y: float) -> tuple[float, float]:
        g = self.ground.ground_z(x, y)
        return g + self.cfg.min_altitude_m, g + self.cfg.max_altitude_m

    def is_free(self, x: float, y: float, z: float, band: bool = True) -> bool:
        """No map point within the sphere (plus a margin), and (``band``) inside the altitude
        band."""
        self.checks += 1
        if band:
            lo, hi = self.altitude_band(x, y)
            if not lo <= z <= hi:
                return False
        if self.free is not None and not self.free.is_free(x, y, z):
            return False
        if len(self._points) == 0:
            return True
        tree = self._tree(np.array([[x, y]], dtype=np.float64))
        if tree is None:
            return True
        d, _ = tree.query((x, y, z), distance_upper_bound=self.reach)
        return not math.isfinite(d)

    def _every(self) -> cKDTree | None:
        """The k-d tree of all the points (None without points)."""
        if self._all is None and len(self._points):
            self._all = kdtree(self._points)
        return self._all

    def distance(self, xyz: np.ndarray) -> float:
        """Distance from ``xyz`` to the nearest map point (inf without points)."""
        tree = self._every()
        return math.inf if tree is None else float(tree.query(np.asarray(xyz, float))[0])

    def nearest(self, xyz: np.ndarray) -> np.ndarray | None:
        """The map point nearest to ``xyz`` (None without points)."""
        tree = self._every()
        return None if tree is None else tree.data[tree.query(np.asarray(xyz, float))[1]]

    def free_many(self, xyz: np.ndarray, band: bool = True) -> np.ndarray:
        """(N,) bool: :meth:`is_free` of many sphere centres at once."""
        xyz = np.asarray(xyz, dtype=np.float64)
        self.checks += len(xyz)
        ok = np.ones(len(xyz), dtype=bool)
        if band:
            g = self.ground.ground_z_many(xyz[:, :2])
            z = xyz[:, 2] - g
            ok = (z >= self.cfg.min_altitude_m) & (z <= self.cfg.max_altitude_m)
        if self.free is not None:
            ok &= self.free.free_many(xyz)
        if len(self._points) and ok.any():
            q = xyz[ok]
            tree = self._tree(q[:, :2])
            if tree is not None:
                d, _ = tree.query(q, distance_upper_bound=self.reach)
                ok[ok] = ~np.isfinite(d)
        return ok
