"""The rover's traversability layer: where it may drive, from what its cameras measured.

Planetary rovers drive only over terrain they have assessed (MER and MSL's GESTALT,
Perseverance's ENav with its approximate clearance evaluation, ACE). This layer does the same
for the rover, apart from the planner-facing occupancy the study is about:

- **A 2.5D height map from observed returns only**: the mast camera's (out to
  ``traverse.mast_range_m``) and both hazard cameras' depth, back-projected at the poses the
  rover publishes. Per ``cell_m`` cell it keeps the lowest return and the highest return
  within the body's reach over it (``body_top_m`` plus the side margin: what stands higher
  is an overhang the rover passes under). A cell is *known* once a return lands in it, or
  once the rover has stood on it (the body's footprint, widened by the side margin, at every
  pose it reached). A cell re-observed ``STALE_STEPS`` or more steps after its last update
  starts again from the new frame, so that pose drift between old and new frames does not
  pile up into false steps. A predicted point never enters it: a prediction may block a
  motion (the map's own collision check, :mod:`planner.collision`), never make one safe.
- **A search-time check** (:meth:`TerrainMap.free`), cheap enough for OMPL's thousands of
  calls a step: the body is covered by three discs along its axis, and a pose is free when
  no disc's centre lies within its radius of an unknown cell (the body itself) or of an
  obstacle cell (the body widened by the side margin; a cell standing higher over the local
  ground plane, fitted to the cells within 0.3 m, than the belly allows: a rock, not a
  slope). Both masks are dilated once a step, over a window around the rover that holds
  every state the planner can reach this step. The same local plane is the measured ground
  the planner-facing map's obstacles are measured from where it is known (:meth:`ground_at`).
- **ACE** (:meth:`TerrainMap.assess`) on every motion the rover is sent along, every
  ``ACE_SPACING_M`` and 5 degrees of it: under the body nothing unknown; the four wheels'
  patches each no rougher than ``wheel_drop_m`` about the wheels' plane; the plane through
  the wheels no steeper than ``max_roll_deg`` / ``max_pitch_deg``, and no wheel off it by
  more than
  ``wheel_drop_m``; nothing under the body (widened by the side margin) higher over that
  plane than the ground clearance less ``belly_margin_m`` (0.18 m), nor a hole under it
  deeper than ``wheel_drop_m``. A refused motion is counted by the first hazard found
  (:data:`HAZARDS`), as is a candidate goal the layer refuses (:meth:`why_not`).
- **A way back** (:meth:`TerrainMap.backout`): the poses of the last steps, most recent first,
  checked by ACE alone: the rover's body stood at each of them, so no prediction there can
  be real.

Everything is in the frame the rover believes it is in (with drift, the drifted one), as an
onboard navigation system would have it.
"""

from __future__ import annotations

import math
from collections import Counter
from collections.abc import Sequence

import numpy as np

from rovergate.config import MissionConfig
from rovergate.geometry import HAZCAMS, densify_se2, hazcam_from_base, rot_z
from rovergate.types import CameraIntrinsics, ExecutionReport, PlanPath, TraversabilityGrid

UNKNOWN, BELLY, WHEEL_DROP, TILT = "unknown", "belly", "wheel-drop", "tilt"
#: The hazards a motion is refused for, in the order they are checked at each pose.
HAZARDS = (UNKNOWN, WHEEL_DROP, TILT, BELLY)

#: Spacing of ACE's poses along a motion (and at most 5 degrees of turn between two).
ACE_SPACING_M = 0.1
ACE_TURN_RAD = math.radians(5.0)
#: A pose within 0.1 m of one the trail holds from the last this many steps is a return to
#: it: the trail is cut back to it (TerrainMap.add_base).
BACK_STEPS_KEPT = 12
#: Within this distance of a start that ACE refuses, a motion may show the start's hazard.
LEAVE_M = 0.5
#: A cell last updated this many steps before a frame that sees it again starts afresh.
STALE_STEPS = 5
#: Half-side of the window the search-time masks cover around the rover (metres): a step's
#: beam looks ahead three motions of ``max_step_m``; states outside are not free.
WINDOW_M = 10.5
#: Half-side (cells) of the window of the local ground plane an obstacle cell stands out of.
GROUND_WINDOW = 3


def _window_reduce(a: np.ndarray, r: int, op) -> np.ndarray:
    """``op`` (np.minimum or np.maximum) over each (2r+1)^2 box, edges padded with the
    identity of ``op``."""
    if r == 0:
        return a.copy()
    fill = {np.minimum: np.inf, np.maximum: -np.inf}[op]
    p = np.pad(a, r, constant_values=fill)
    h, w = a.shape
    rows = p[:, :w].copy()
    for dj in range(1, 2 * r + 1):
        rows = op(rows, p[:, dj:dj + w])
    out = rows[:h].copy()
    for di in range(1, 2 * r + 1):
        out = op(out, rows[di:di + h])
    return out


def plane_residual(known: np.ndarray, elev: np.ndarray, r: int, keep: np.ndarray | None = None
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Each cell's height over the least-squares plane of the known cells (those of ``keep``,
    if given) in the (2r+1)^2 window around it: (residual, fitted, plane) with fitted False
    where fewer than 6 cells were known (residual 0 there), plane the plane's height at the
    cell."""
    from scipy.ndimage import uniform_filter  # (the rover's planner only: 0.25 s to import)
    K = (known if keep is None else known & keep).astype(np.float64)
    h, w = K.shape
    Y, X = np.mgrid[0:h, 0:w].astype(np.float64)
    Z = np.where(known, elev, 0.0) * K
    # The window sums of the nine moments at once (zeros beyond the edges).
    moments = np.stack([K, K * X, K * Y, Z, K * X * X, K * X * Y, K * Y * Y, Z * X, Z * Y])
    size = 2 * r + 1
    sums = uniform_filter(moments, size=(1, size, size), mode="constant") * (size * size)
    n, sx, sy, sz, sxx, sxy, syy, sxz, syz = sums
    fitted = n >= 6
    nn = np.where(fitted, n, 1.0)
    # Centred on each cell: the plane z = a + b (x - X) + c (y - Y), a its height there.
    mx, my, mz = sx / nn, sy / nn, sz / nn
    cxx, cxy, cyy = sxx / nn - mx * mx, sxy / nn - mx * my, syy / nn - my * my
    cxz, cyz = sxz / nn - mx * mz, syz / nn - my * mz
    det = cxx * cyy - cxy * cxy
    ok = fitted & (det > 1e-9)
    d = np.where(ok, det, 1.0)
    b = np.where(ok, (cxz * cyy - cyz * cxy) / d, 0.0)
    c = np.where(ok, (cyz * cxx - cxz * cxy) / d, 0.0)
    a = mz + b * (X - mx) + c * (Y - my)
    res = np.where(fitted & known, np.where(known, elev, 0.0) - a, 0.0)
    return res, fitted, a


def _dilate_disc(mask: np.ndarray, radius_cells: float) -> np.ndarray:
    """Cells within ``radius_cells`` (centre to centre) of a True cell of ``mask``."""
    from scipy.ndimage import distance_transform_edt
    if not mask.any():
        return np.zeros_like(mask)
    return distance_transform_edt(~mask) <= radius_cells


def driven_way(path: PlanPath | None, report: ExecutionReport | None
               ) -> list[tuple[float, float, float, float]]:
    """The states (x, y, yaw, z) between the start and the end of the last step's ``path``
    that the rover drove through, as far as ``report`` says it got (a motion the bumper or
    untraversable ground stopped ends early): the way it came, for the trail."""
    if path is None or report is None or len(path.poses) < 3:
        return []
    states = [(float(p.position[0]), float(p.position[1]), p.yaw, float(p.position[2]))
              for p in path.poses]
    xy = np.array([s[:2] for s in states])
    run = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(xy, axis=0), axis=1))]
    driven = report.executed_fraction * run[-1]
    done = report.executed_fraction >= 1.0
    return [s for s, d in zip(states[1:-1], run[1:-1], strict=True)
            if done or d <= driven - 1e-6]


class TerrainMap:
    """The height map of one mission, and the checks of the rover's motions on it."""

    def __init__(self, cfg: MissionConfig) -> None:
        self.cfg = cfg
        t, r = cfg.traverse, cfg.rover
        self.cell = t.cell_m
        b = cfg.scene.bounds_m
        margin = 3.0
        self.ox, self.oy = b[0] - margin, b[1] - margin
        self.shape = (int(math.ceil((b[4] - b[1] + 2 * margin) / self.cell)),
                      int(math.ceil((b[3] - b[0] + 2 * margin) / self.cell)))
        self.lo = np.full(self.shape, np.inf)
        self.top = np.full(self.shape, -np.inf)
        self.updated = np.full(self.shape, -(10 ** 9), dtype=np.int64)
        self.band_m = r.body_top_m + t.side_margin_m
        self.belly_m = r.clearance_m - t.belly_margin_m
        self.trail: list[tuple[float, float, float]] = []
        """The way the rover came: the base states (x, y, yaw) it drove through, oldest
        first (each step's path as far as it was driven, then where it stood), cut back
        where it returned (a back-out)."""
        self.trail_steps: list[int] = []
        """The step (the count of bases taken in, from 0) of each state of :attr:`trail`."""
        self.visited: list[tuple[float, float]] = []
        """Where the rover stood at each step, oldest first, never cut."""
        self.refused: Counter[str] = Counter()
        """Motions refused so far, by hazard."""
        self._rays: dict[tuple, np.ndarray] = {}
        h = cfg.hazcam
        self.hazcam_k = CameraIntrinsics.from_fov(h.width_px, h.height_px, h.vfov_deg)
        # The body as discs along its axis: three of them cover the body (unknown check) and
        # the body widened by the side margin (obstacle check).
        half_l = r.length_m / 2
        self._disc_offsets = (-2 * half_l / 3, 0.0, 2 * half_l / 3)
        slab = half_l / 3
        diag = math.sqrt(2) / 2  # a cell's centre to its corner, in cells
        # (Unknown ground is judged exactly by ACE on every motion; the search's discs only
        # keep it from planning through the unknown, so they are not widened by a cell.)
        self._r_unknown = math.hypot(slab, r.width_m / 2) / self.cell
        self._r_obstacle = (math.hypot(slab + t.side_margin_m, r.width_m / 2 + t.side_margin_m)
                            / self.cell + diag)
        # ACE's samples in the body frame: the body (must be known), the ring of the side
        # margin around it, and the four wheels' patches at its corners.
        s = self.cell / 2
        m = t.side_margin_m
        u = np.arange(-half_l - m, half_l + m + 1e-9, s)
        v = np.arange(-r.width_m / 2 - m, r.width_m / 2 + m + 1e-9, s)
        U, V = np.meshgrid(u, v)
        self._samples = np.c_[U.ravel(), V.ravel()]
        self._in_body = ((np.abs(self._samples[:, 0]) <= half_l + 1e-9)
                         & (np.abs(self._samples[:, 1]) <= r.width_m / 2 + 1e-9))
        wheel = 0.2
        wu = np.arange(-wheel / 2, wheel / 2 + 1e-9, s)
        WU, WV = np.meshgrid(wu, wu)
        patch = np.c_[WU.ravel(), WV.ravel()]
        self._wheels = np.array([[a * (half_l - wheel / 2), b * (r.width_m / 2 - wheel / 2)]
                                 for a, b in ((1, 1), (1, -1), (-1, 1), (-1, -1))])
        self._patches = self._wheels[:, None, :] + patch[None]
        A = np.c_[np.ones(4), self._wheels]
        self._wheel_fit = np.linalg.pinv(A)
        self._tan_roll = math.tan(math.radians(t.max_roll_deg))
        self._tan_pitch = math.tan(math.radians(t.max_pitch_deg))
        self._tan_slope = math.tan(math.radians(r.slope_limit_deg))
        self._win: tuple[int, int, np.ndarray] | None = None

    # --- building the map -------------------------------------------------------------------

    def add_step(self, step: int, T_map_base: np.ndarray, mast: tuple | None,
                 hazcams: dict[str, np.ndarray], way: Sequence[tuple] = ()) -> None:
        """Take in one step: where the rover stands (``T_map_base``, 4 x 4), the mast frame
        ``(T_map_camera, intrinsics, depth)``, the hazard cameras' depth by name (their
        poses follow from the base pose and the mounting) and ``way``, the states (x, y,
        yaw) the rover drove through since the last step (:func:`driven_way`)."""
        self.add_base(T_map_base, way)
        if mast is not None:
            T_cam, k, depth = mast
            self.add_frame(step, T_cam, k, depth, self.cfg.traverse.mast_range_m)
        for name in HAZCAMS:
            depth = hazcams.get(name)
            if depth is not None and depth.size:
                self.add_frame(step, hazcam_from_base(T_map_base, self.cfg.hazcam, name),
                               self.hazcam_k, depth, self.cfg.hazcam.max_range_m)
        self._win = None

    def add_base(self, T_map_base: np.ndarray, way: Sequence[tuple] = ()) -> None:
        """The rover stands here, having driven through ``way`` (states x, y, yaw and, if
        given, z) since the last step: the cells of its footprint here and along the way are
        known (:meth:`_stand`), and the way goes on the trail."""
        R, p = T_map_base[:3, :3], T_map_base[:3, 3]
        yaw = math.atan2(R[1, 0], R[0, 0])
        n = len(self.visited)
        # Back where it drove a few steps ago (a back-out): the way since is a dead end it
        # left, not a way back (and the back-out retraced it).
        returned = False
        for k in range(len(self.trail) - 1, -1, -1):
            if self.trail_steps[k] < n - BACK_STEPS_KEPT:
                break
            q = self.trail[k]
            if math.hypot(q[0] - p[0], q[1] - p[1]) < 0.1:
                del self.trail[k:], self.trail_steps[k:]
                returned = True
                break
        for q in () if returned else way:  # (level, at the height the path gave it)
            self.trail.append((float(q[0]), float(q[1]), float(q[2])))
            self.trail_steps.append(n)
            self._stand(rot_z(q[2]), np.array([q[0], q[1], q[3] if len(q) > 3 else p[2]]))
        self.trail.append((float(p[0]), float(p[1]), yaw))
        self.trail_steps.append(n)
        self.visited.append((float(p[0]), float(p[1])))
        self._stand(R, p)

    def _stand(self, R: np.ndarray, p: np.ndarray) -> None:
        """The body stood (or drove) at rotation ``R``, position ``p``: its footprint's
        cells, widened by the side margin, are known; where no return landed, their ground
        is the plane the base stood on."""
        xy_body = self._samples
        pts = np.c_[xy_body, np.zeros(len(xy_body))] @ R.T + p
        i, j = self._cells(pts[:, :2])
        ok = (i >= 0) & (i < self.shape[0]) & (j >= 0) & (j < self.shape[1])
        i, j, z = i[ok], j[ok], pts[ok, 2]
        blank = ~np.isfinite(self.lo[i, j])
        self.lo[i[blank], j[blank]] = z[blank]
        self.top[i[blank], j[blank]] = z[blank]

    def _camera_rays(self, k: CameraIntrinsics) -> tuple[np.ndarray, np.ndarray]:
        """Each pixel's ray (x/z, y/z, 1) in the optical frame, and its length (range over
        z-depth), computed once per camera."""
        key = (k.width, k.height, k.fx, k.fy, k.cx, k.cy)
        if key not in self._rays:
            u, v = np.meshgrid(np.arange(k.width, dtype=np.float64),
                               np.arange(k.height, dtype=np.float64))
            rays = np.stack([(u - k.cx) / k.fx, (v - k.cy) / k.fy, np.ones_like(u)], axis=-1)
            self._rays[key] = (rays, np.sqrt((rays ** 2).sum(-1)))
        return self._rays[key]

    def add_frame(self, step: int, T_map_camera: np.ndarray, k: CameraIntrinsics,
                  depth: np.ndarray, max_range_m: float) -> None:
        """Back-project one depth image's valid returns (within ``max_range_m``) into the
        height map."""
        rays, length = self._camera_rays(k)
        if rays.shape[:2] != depth.shape:
            return  # (an image that does not match its intrinsics carries nothing usable)
        with np.errstate(invalid="ignore"):
            valid = (depth > 0) & (depth * length <= max_range_m)  # NaN and +Inf: False
        if not valid.any():
            return
        z = depth[valid].astype(np.float64)
        P = (rays[valid] * z[:, None]) @ T_map_camera[:3, :3].T + T_map_camera[:3, 3]
        self.add_points(step, P)

    def add_points(self, step: int, P: np.ndarray) -> None:
        """Take in (N, 3) measured points (map frame) seen at ``step``. Per point, with the
        cells repeated as often as points fall in them: every update below writes the same
        value for each repeat, so the order does not matter."""
        i, j = self._cells(P[:, :2])
        ok = (i >= 0) & (i < self.shape[0]) & (j >= 0) & (j < self.shape[1])
        flat = (i * self.shape[1] + j)[ok]
        z = P[ok, 2]
        lo, top, upd = self.lo.reshape(-1), self.top.reshape(-1), self.updated.reshape(-1)
        stale = flat[upd[flat] <= step - STALE_STEPS]
        lo[stale], top[stale] = np.inf, -np.inf
        upd[flat] = step
        old_lo, old_top = lo[flat], top[flat]
        np.minimum.at(lo, flat, z)
        new_lo = lo[flat]
        # What was kept over the old lowest return is measured again from the new one: all of
        # it overhead now (forgotten), or partly (capped at the band: an obstacle at most).
        overhead = old_lo > new_lo + self.band_m
        top[flat[overhead]] = -np.inf
        capped = ~overhead & (old_top > new_lo + self.band_m)
        top[flat[capped]] = new_lo[capped] + self.band_m
        keep = z <= new_lo + self.band_m
        np.maximum.at(top, flat[keep], z[keep])

    def _cells(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return (np.floor((xy[:, 1] - self.oy) / self.cell).astype(np.int64),
                np.floor((xy[:, 0] - self.ox) / self.cell).astype(np.int64))

    # --- the layers of a step -----------------------------------------------------------

    def elevation(self, i0: int, i1: int, j0: int, j1: int
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(known, top, ground) of the cells [i0:i1, j0:j1]: each cell's highest return within
        the body's reach (what stands there) and its lowest (the ground a wheel could drop
        to), NaN where unknown. An unknown cell with at least 6 known neighbours takes their
        highest top and lowest ground (a hole between returns, not a gap in the terrain)."""
        top, lo = self.top[i0:i1, j0:j1], self.lo[i0:i1, j0:j1]
        known = np.isfinite(top)
        elev, ground = np.where(known, top, np.nan), np.where(known, lo, np.nan)
        p = np.pad(known, 1).astype(np.int8)
        h, w = known.shape
        n = sum(p[1 + di:1 + di + h, 1 + dj:1 + dj + w]
                for di in (-1, 0, 1) for dj in (-1, 0, 1) if di or dj)
        hole = ~known & (n >= 6)
        if hole.any():
            high = _window_reduce(np.where(known, top, -np.inf), 1, np.maximum)
            low = _window_reduce(np.where(known, lo, np.inf), 1, np.minimum)
            elev, ground = np.where(hole, high, elev), np.where(hole, low, ground)
            known = known | hole
        return known, elev, ground

    def prepare(self, x: float, y: float) -> None:
        """Build this step's search-time masks around (x, y) (once a step: the planner calls
        it with the rover's position)."""
        w = int(math.ceil(WINDOW_M / self.cell))
        ci = int(math.floor((y - self.oy) / self.cell))
        cj = int(math.floor((x - self.ox) / self.cell))
        i0, j0 = min(max(ci - w, 0), self.shape[0] - 1), min(max(cj - w, 0), self.shape[1] - 1)
        i1, j1 = max(min(ci + w + 1, self.shape[0]), i0 + 1), max(min(cj + w + 1, self.shape[1]),
                                                                   j0 + 1)
        known, elev, ground = self.elevation(i0, i1, j0, j1)
        # Over the local ground plane, fitted without the cells that stand out of their
        # 3 x 3 neighbourhood by half the belly's limit (a rock's edge; a 25-degree slope
        # rises 0.07 m over a cell's diagonal), so that a rock does not lift the plane it is
        # measured from: slopes are not obstacles, rocks are. And an edge: where the lowest
        # returns of a 3 x 3 neighbourhood span more than the belly's limit (a slab's or a
        # ledge's side, which the highest returns smear over a cell).
        low = _window_reduce(np.where(known, elev, np.inf), 1, np.minimum)
        res, fitted, plane = plane_residual(known, elev, GROUND_WINDOW,
                                            keep=elev - low <= self.belly_m / 2)
        g = np.where(known, ground, np.nan)
        span = (_window_reduce(np.where(known, ground, -np.inf), 1, np.maximum)
                - _window_reduce(np.where(known, ground, np.inf), 1, np.minimum))
        obstacle = known & (np.where(fitted, res > self.belly_m, elev - low > self.belly_m)
                            | (np.isfinite(g) & (span > self.belly_m)))
        self._unknown_near = _dilate_disc(~known, self._r_unknown)
        blocked = self._unknown_near | _dilate_disc(obstacle, self._r_obstacle)
        self._win = (i0, j0, blocked)
        self._known, self._elev, self._low, self._obstacle = known, elev, ground, obstacle
        self._ground = np.where(fitted, plane, np.nan)

    def ground_at(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(known, height) of the measured ground plane under (N, 2) positions: the local
        plane the obstacle cells stand out of, where enough of the ground around was seen
        (known False elsewhere, and outside this step's window)."""
        i0, j0, _ = self._win
        i, j = self._cells(np.asarray(xy, dtype=np.float64))
        i, j = i - i0, j - j0
        h, w = self._ground.shape
        inside = (i >= 0) & (i < h) & (j >= 0) & (j < w)
        z = np.full(len(i), np.nan)
        z[inside] = self._ground[i[inside], j[inside]]
        return np.isfinite(z), z

    def grid(self, step: int) -> TraversabilityGrid:
        """This step's window as an occupancy grid: -1 unknown, 0 clear, 100 obstacle."""
        if self._win is None:
            self.prepare(*self.trail[-1][:2])
        i0, j0, _ = self._win
        cells = np.where(self._known, np.where(self._obstacle, 100, 0), -1).astype(np.int8)
        return TraversabilityGrid(step, cells, self.cell,
                                  (self.ox + j0 * self.cell, self.oy + i0 * self.cell))

    def known_cells(self) -> int:
        """Cells observed (or stood on) so far."""
        return int(np.isfinite(self.top).sum())

    def free(self, x: float, y: float, yaw: float) -> bool:
        """The search-time check (module docstring): no disc of the body near unknown or
        obstacle cells."""
        if self._win is None:
            self.prepare(*(self.trail[-1][:2] if self.trail else (x, y)))
        i0, j0, blocked = self._win
        c, s = math.cos(yaw), math.sin(yaw)
        h, w = blocked.shape
        for a in self._disc_offsets:
            i = math.floor((y + a * s - self.oy) / self.cell) - i0
            j = math.floor((x + a * c - self.ox) / self.cell) - j0
            if not (0 <= i < h and 0 <= j < w) or blocked[i, j]:
                return False
        return True

    def assess(self, x: float, y: float, yaw: float) -> str | None:
        """ACE at one pose: the first hazard found (:data:`HAZARDS`), or None."""
        if self._win is None:
            self.prepare(*(self.trail[-1][:2] if self.trail else (x, y)))
        i0, j0, _ = self._win
        known, elev, low = self._known, self._elev, self._low
        c, s = math.cos(yaw), math.sin(yaw)
        R = np.array([[c, -s], [s, c]])

        def look(body_xy: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
            xy = body_xy @ R.T + (x, y)
            i, j = self._cells(xy)
            i, j = i - i0, j - j0
            ok = (i >= 0) & (i < known.shape[0]) & (j >= 0) & (j < known.shape[1])
            i, j = np.where(ok, i, 0), np.where(ok, j, 0)
            return (ok & known[i, j], np.where(ok, elev[i, j], np.nan),
                    np.where(ok, low[i, j], np.nan))

        k_s, z_s, g_s = look(self._samples)
        if not k_s[self._in_body].all():
            return UNKNOWN
        k_w, _, g_w = look(self._patches.reshape(-1, 2))
        k_w, g_w = k_w.reshape(4, -1), g_w.reshape(4, -1)
        if not k_w.all():
            return UNKNOWN
        t = self.cfg.traverse
        heights = g_w.max(axis=1)  # each wheel rests on the highest ground of its patch
        coef = self._wheel_fit @ heights
        # A wheel's patch, less the wheels' plane, spans no more than the drop limit (the
        # plane taken out: a patch on a slope is not rough), and each wheel sits on the plane.
        # The ground is each cell's lowest return: a ledge's edge stays sharp in it.
        rel = g_w - (coef[0] + self._patches @ coef[1:])
        if (rel.max(axis=1) - rel.min(axis=1) > t.wheel_drop_m).any():
            return WHEEL_DROP
        if np.abs(heights - np.c_[np.ones(4), self._wheels] @ coef).max() > t.wheel_drop_m:
            return WHEEL_DROP
        if (abs(coef[1]) > self._tan_pitch or abs(coef[2]) > self._tan_roll
                or math.hypot(coef[1], coef[2]) > self._tan_slope):
            return TILT
        plane = coef[0] + self._samples @ coef[1:]
        over = np.where(k_s, z_s - plane, 0.0)  # what stands there: each cell's highest
        if over.max() > self.belly_m:
            return BELLY
        under = np.where(k_s, plane - g_s, 0.0)
        if under[self._in_body].max() > t.wheel_drop_m:
            return WHEEL_DROP
        return None

    def why_not(self, x: float, y: float, yaw: float) -> str | None:
        """The hazard that makes the layer refuse a pose, counted in :attr:`refused`: ACE's,
        or, where ACE passes and the search-time check does not, ``unknown`` or ``belly``
        by the mask that blocks it; None if the layer allows the pose."""
        hazard = self.assess(x, y, yaw)
        if hazard is None and not self.free(x, y, yaw):
            hazard = UNKNOWN if not self._known_discs(x, y, yaw) else BELLY
        if hazard is not None:
            self.refused[hazard] += 1
        return hazard

    def _known_discs(self, x: float, y: float, yaw: float) -> bool:
        i0, j0, _ = self._win
        c, s = math.cos(yaw), math.sin(yaw)
        h, w = self._unknown_near.shape
        for a in self._disc_offsets:
            i = math.floor((y + a * s - self.oy) / self.cell) - i0
            j = math.floor((x + a * c - self.ox) / self.cell) - j0
            if not (0 <= i < h and 0 <= j < w) or self._unknown_near[i, j]:
                return False
        return True

    def admit(self, states: list[tuple[float, float, float]]) -> str | None:
        """ACE along a motion through ``states``: the first hazard found, counted in
        :attr:`refused`, or None. The first state, where the rover stands, is not judged; if
        ACE refuses it (new returns showed a rock's flank under a wheel, say), poses within
        ``LEAVE_M`` of it may show the same hazard (the rover is leaving it), never another,
        and never unknown ground."""
        poses = densify_se2(states, ACE_SPACING_M, ACE_TURN_RAD)
        if not poses:
            return None
        here = self.assess(*poses[0])
        for pose in poses[1:]:
            hazard = self._blocking(pose, poses[0], here)
            if hazard is not None:
                self.refused[hazard] += 1
                return hazard
        return None

    def _blocking(self, pose: tuple, start: tuple, start_hazard: str | None) -> str | None:
        """ACE's hazard at ``pose`` on a motion from ``start`` (whose own hazard is
        ``start_hazard``), or None where it passes or where it is leaving the start: within
        ``LEAVE_M`` of it, showing the start's own hazard, never unknown ground."""
        hazard = self.assess(*pose)
        if (hazard is not None and hazard == start_hazard and hazard != UNKNOWN
                and math.hypot(pose[0] - start[0], pose[1] - start[1]) <= LEAVE_M):
            return None
        return hazard

    def dither_spots(self) -> np.ndarray:
        """(K, 2) where the rover stood at the steps of the last ``dither_memory`` that ended
        a dither (``TraverseConfig.dither_window``): places its planner should leave."""
        t = self.cfg.traverse
        p = np.asarray(self.visited, dtype=np.float64).reshape(-1, 2)
        w = t.dither_window
        if len(p) <= w:
            return np.zeros((0, 2))
        moved = np.linalg.norm(p[w:] - p[:-w], axis=1)
        ends = np.flatnonzero(moved < t.dither_min_m) + w
        return p[ends[ends >= len(p) - t.dither_memory]]

    def backout(self, here: tuple[float, float, float], budget_m: float, steps: int,
                extra_ok=None) -> list[tuple[float, float, float]]:
        """The way back along the way the rover came in its last ``steps`` steps (most
        recent first, the rover keeping each state's heading, driving backwards), at most
        ``budget_m`` long, as far as ACE (and ``extra_ok``, a state check) allows, with
        :meth:`admit`'s leave rule (a start ACE refuses may show its hazard within
        ``LEAVE_M``); empty if not one state back. The rover drove through every one of them,
        so the way is over known ground, swept as it was swept coming."""
        way: list[tuple[float, float, float]] = []
        last, length = here, 0.0
        start_hazard = self.assess(*here)
        back: list[tuple[float, float, float]] = []
        if steps and self.trail:
            first = self.trail_steps[-1] - steps  # back to where it stood that step
            j = next((k for k in range(len(self.trail) - 1, -1, -1)
                      if self.trail_steps[k] <= first), 0)
            back = self.trail[j:-1]
        for p in reversed(back):
            d = math.hypot(p[0] - last[0], p[1] - last[1])
            if d < 0.05:
                continue
            if length + d > budget_m:
                f = (budget_m - length) / d
                if f * d < 0.05:
                    break
                p = (last[0] + f * (p[0] - last[0]), last[1] + f * (p[1] - last[1]), p[2])
                d = f * d
            seg = densify_se2([last, p], ACE_SPACING_M, ACE_TURN_RAD)[1:]
            if any(self._blocking(s, here, start_hazard) is not None
                   or (extra_ok is not None and not extra_ok(s)) for s in seg):
                break
            way.append(p)
            last, length = p, length + d
            if length >= budget_m - 1e-9:
                break
        return way
