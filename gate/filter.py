"""The observation-gated filter (paper, equation 4).

A predicted point x is *unsupported* at step t when it has been inside at least K acquired
camera frustums, n_t(x) >= K, and no observed surface point lies within epsilon of it:

    U_t = { x in O_hat_t : n_t(x) >= K  and  min_{p in S_t} ||x - p|| > epsilon }

The planner then receives S_t together with O_hat_t minus U_t. U_t is recomputed from scratch
every step over the current prediction and all frustums so far, so later surface support
near a point restores it. Frustum inclusion is the paper's exposure proxy: inside the image,
in front of the camera, between the sensor's minimum and maximum range. It ignores occlusion.

The support test is incremental and exact (:class:`SurfaceSupport`): S_t only grows, so a
prediction supported once stays supported while the radius does not shrink, and the surface
is indexed in a large k-d tree rebuilt now and then plus a small one of what came since.
"""

from __future__ import annotations

import numpy as np

from gate.views import Frustums, block_groups, extends, pixels, row_keys
from rovergate.geometry import project
from rovergate.spatial import kdtree
from rovergate.types import CameraIntrinsics

_CHUNK_FRUSTUMS = 16


class SurfaceSupport:
    """Which points have an observed surface point within a radius, step after step.

    Exactly ``min_{p in S} ||x - p|| <= radius`` (as one k-d tree of S answers it), for any
    sequence of calls, computed incrementally on two facts. The surface only grows at its end
    (the mapper appends; a surface that is not an extension of the last call's, as after a
    restart, forgets what was remembered, and one that is not an extension of the indexed
    prefix rebuilds the tree).
    So a point supported at one step is supported at every later one with a radius no
    smaller: points are remembered by their exact coordinates (predictions repeat from one
    step to the next), and only the others are queried. The surface is indexed in a k-d tree
    of a prefix, rebuilt when what came since exceeds ``REBUILD_SHARE`` of it, and a small
    tree of that tail; a point's distance is the smaller of the two trees' answers.
    """

    #: The tail grows to this share of the indexed prefix (and at least ``REBUILD_MIN``
    #: points) before the prefix's tree is rebuilt.
    REBUILD_SHARE = 0.25
    REBUILD_MIN = 2048

    def __init__(self) -> None:
        self._tree = None
        self._n = 0                     # surface points in the prefix's tree
        self._last: np.ndarray | None = None   # the last of them, to tell an extension
        self._seen = (0, None)          # the last call's surface: its length and last point
        self._radius = 0.0              # the radius the remembered points were supported at
        self._supported = row_keys(np.zeros((0, 3)))  # sorted rows of points known supported

    def _index(self, surface: np.ndarray) -> np.ndarray:
        """Bring the prefix's tree up to date; returns the tail not in it."""
        if not extends(surface, *self._seen):  # what was remembered may be gone
            self._supported = self._supported[:0]
        self._seen = (len(surface), np.array(surface[-1]) if len(surface) else None)
        n = self._n
        if not extends(surface, n, self._last):
            self._tree, self._n, n = None, 0, 0
        if self._tree is None or len(surface) - n > max(self.REBUILD_SHARE * n,
                                                        self.REBUILD_MIN):
            self._tree = kdtree(surface) if len(surface) else None
            self._n = n = len(surface)
            self._last = np.array(surface[-1]) if n else None
        return surface[n:]

    def supported(self, points: np.ndarray, surface: np.ndarray, radius: float) -> np.ndarray:
        """(N,) bool: an observed surface point lies within ``radius`` of the point (both
        taken as float32, the map's own precision)."""
        points = np.asarray(points, dtype=np.float32)
        surface = np.asarray(surface, dtype=np.float32)
        out = np.zeros(len(points), dtype=bool)
        if len(points) == 0 or len(surface) == 0:
            return out
        tail = self._index(surface)
        if radius < self._radius:
            self._supported = self._supported[:0]
        self._radius = radius
        rows = row_keys(points)
        known = self._supported
        if len(known):
            i = np.minimum(np.searchsorted(known, rows), len(known) - 1)
            out = known[i] == rows
        ask = np.flatnonzero(~out)
        if len(ask) and self._tree is not None:
            d, _ = self._tree.query(points[ask], k=1, distance_upper_bound=radius)
            out[ask] = ~(d > radius)
            ask = ask[d > radius]
        if len(ask) and len(tail):
            d, _ = kdtree(tail).query(points[ask], k=1, distance_upper_bound=radius)
            out[ask] = ~(d > radius)
        self._supported = np.sort(rows[out])  # what the next step's points may repeat
        return out


class ObservationGate:
    """Keeps the frustums acquired so far and computes U_t of equation 4."""

    def __init__(self, k: int, epsilon_m: float, min_range_m: float, max_range_m: float) -> None:
        if k < 1 or epsilon_m <= 0:
            raise ValueError(f"gate needs k >= 1 and epsilon > 0, got k={k}, epsilon={epsilon_m}")
        self.k = k
        self.epsilon_m = epsilon_m
        self.min_range_m = min_range_m
        self.max_range_m = max_range_m
        self._R_cam_map: list[np.ndarray] = []
        self._t_cam_map: list[np.ndarray] = []
        self._intrinsics: list[CameraIntrinsics] = []
        self._support = SurfaceSupport()
        # Which blocks of points each frame may see: a frame is tested only against the
        # points of the blocks its frustum meets (gate.views; the counts are unchanged).
        self._frustums = Frustums(min_range_m, max_range_m)

    def _near(self, points_map: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """For each frame that may see any of the points: ``(frames (F,), meets (F, B),
        block (N,))``, the frames' indices, which blocks each frame's frustum meets, and each
        point's block (a frame cannot contain a point outside the blocks it meets). Kept per
        block, not per point: F x N would be tens of megabytes late in a mission."""
        centres, block = block_groups(points_map)
        meets = self._frustums.meets(centres)
        frames = np.flatnonzero(meets.any(axis=1))
        return frames, meets[frames], block

    @property
    def n_frustums(self) -> int:
        return len(self._R_cam_map)

    def add_frustum(self, T_map_camera: np.ndarray, intrinsics: CameraIntrinsics) -> None:
        """Record the frustum of one acquired frame (optical-frame pose in map)."""
        R = T_map_camera[:3, :3].T
        self._R_cam_map.append(R)
        self._t_cam_map.append(-R @ T_map_camera[:3, 3])
        self._intrinsics.append(intrinsics)
        self._frustums.add(T_map_camera, intrinsics)

    def add_frame(self, T_map_camera: np.ndarray, intrinsics: CameraIntrinsics,
                  depth: np.ndarray, covariance: np.ndarray | None = None) -> None:
        """Record an acquired frame: its frustum (the frustum gate reads neither the depth
        nor the pose's covariance)."""
        self.add_frustum(T_map_camera, intrinsics)

    @property
    def support_radius_m(self) -> float:
        """How far from a predicted point an observed one supports it: epsilon."""
        return self.epsilon_m

    def exposure_counts(self, points_map: np.ndarray, stop_at: int | None = None) -> np.ndarray:
        """n_t(x): (N,) int32 number of recorded frustums that contain each point.

        ``stop_at``: a point's count may stop growing once it reaches this many (only whether
        n_t >= K matters to the filter), which lets the count skip it in later frustums."""
        counts = np.zeros(len(points_map), dtype=np.int32)
        if len(points_map) == 0 or not self._R_cam_map:
            return counts
        frames, meets, block = self._near(points_map)
        active = np.arange(len(points_map))
        for lo in range(0, len(frames), _CHUNK_FRUSTUMS):
            chunk = frames[lo:lo + _CHUNK_FRUSTUMS]
            if stop_at is not None:
                active = active[counts[active] < stop_at]
            reached = meets[lo:lo + _CHUNK_FRUSTUMS].any(axis=0)
            active_here = active[reached[block[active]]]
            if len(active_here) == 0:
                continue
            p = points_map[active_here].astype(np.float64)
            R = np.stack([self._R_cam_map[f] for f in chunk])     # (F, 3, 3)
            t = np.stack([self._t_cam_map[f] for f in chunk])     # (F, 3)
            ks = [self._intrinsics[f] for f in chunk]
            pc = np.einsum("fij,nj->fni", R, p) + t[:, None, :]          # (F, N, 3)
            per_frame = (np.array([[getattr(k, f)] for k in ks])
                         for f in ("fx", "fy", "cx", "cy", "width", "height"))  # (F, 1) each
            inside = project(pc, *per_frame, self.min_range_m, self.max_range_m)[0]
            counts[active_here] += inside.sum(axis=0, dtype=np.int32)
        return counts

    def supported(self, points_map: np.ndarray, surface_map: np.ndarray) -> np.ndarray:
        """(N,) bool: an observed surface point lies within the support radius of the point
        (epsilon; the surface ``surface_map`` is S_t, which only grows from step to step)."""
        return self._support.supported(points_map, surface_map, self.support_radius_m)

    def unsupported(self, points_map: np.ndarray, surface_map: np.ndarray) -> np.ndarray:
        """(N,) bool mask of U_t: exposed at least K times with no support within epsilon."""
        if len(points_map) == 0:
            return np.zeros(0, dtype=bool)
        # Supported points are never in U_t: count exposures only for the others.
        out = ~self.supported(points_map, surface_map)
        candidates = np.flatnonzero(out)
        out[candidates] = self.exposure_counts(points_map[candidates], stop_at=self.k) >= self.k
        return out


def _all_neighbours(mask: np.ndarray) -> np.ndarray:
    """(H, W) bool: the pixel's 8 neighbours are all set (outside the image is unknown: a
    pixel on the image's edge never is)."""
    padded = np.pad(mask, 1, constant_values=False)
    h, w = mask.shape
    out = np.ones_like(mask)
    for dv in (0, 1, 2):
        for du in (0, 1, 2):
            if (dv, du) != (1, 1):
                out &= padded[dv:dv + h, du:du + w]
    return out


class RayGate(ObservationGate):
    """Equation 4 with ray-consistent exposure (the ``gated-ray`` condition).

    A frame *exposes* a predicted point x only when its depth image says the ray through x
    passed through it: x is in front of the camera within the sensor's usable range, projects
    inside the image, and the return at its pixel is usable and ends at least ``margin_m``
    beyond x. A nearer return (x is hidden: occluded), one within the margin (x is confirmed),
    and an unusable return give no evidence at all. A return is unusable when it is dropped
    (NaN), saturated (+Inf: nothing within range, so where the ray ended is unknown) or
    grazing: the surface it hit is seen at an incidence angle above ``grazing_max_deg``,
    estimated from the depth image's local gradient (``tan(angle) = |grad d| f / d``: a
    plane seen at that angle changes depth by ``d tan(angle) / f`` from one pixel to the
    next). Depth discontinuities, whose mixed returns are least trustworthy, read as grazing.

    With ``beyond_range_passes`` (the ``gated-ray-inf`` condition) a saturated return is
    evidence after all: +Inf says nothing lay within the sensor's range along the pixel, so the
    ray passed through every point nearer than the range, as :mod:`gate.views` reads it, where
    its 8 neighbours saw nothing within range either (beside a silhouette, the nearest pixel
    of a point on the surface's edge may miss it). A dropped or grazing return still gives
    none. This is where the frustum gate's correct
    removals are seen: a hallucinated surface floating against the sky.

        U_t = { x in O_hat_t : n_ray(x) >= K  and  min_{p in S_t} ||x - p|| > epsilon }
    """

    def __init__(self, k: int, epsilon_m: float, min_range_m: float, max_range_m: float,
                 margin_m: float, grazing_max_deg: float,
                 beyond_range_passes: bool = False) -> None:
        if k < 1 or epsilon_m <= 0 or margin_m < 0 or not 0 < grazing_max_deg <= 90:
            raise ValueError(f"the ray gate needs k >= 1, epsilon > 0, margin >= 0 and a "
                             f"grazing angle in (0, 90]; got k={k}, epsilon={epsilon_m}, "
                             f"margin={margin_m}, angle={grazing_max_deg}")
        super().__init__(k, epsilon_m, min_range_m, max_range_m)
        self.margin_m = margin_m
        self.beyond_range_passes = beyond_range_passes
        self.tan_grazing = np.inf if grazing_max_deg >= 90 else np.tan(np.radians(grazing_max_deg))
        self._frames: list[tuple[np.ndarray, np.ndarray, CameraIntrinsics, np.ndarray]] = []

    @property
    def n_frustums(self) -> int:
        return len(self._frames)

    def usable_depth(self, depth: np.ndarray, k: CameraIntrinsics) -> np.ndarray:
        """The depth image with every unusable return (dropped, grazing, and saturated unless
        ``beyond_range_passes``) NaN; a saturated return that passes stays +Inf."""
        d = np.asarray(depth, dtype=np.float32).copy()
        beyond = np.isposinf(d)
        d[~np.isfinite(d)] = np.nan
        if np.isfinite(self.tan_grazing):
            with np.errstate(invalid="ignore"):
                gv, gu = np.gradient(d.astype(np.float64))
                tan = np.hypot(gu * k.fx, gv * k.fy) / d
            d[~(tan <= self.tan_grazing)] = np.nan  # NaN neighbours: no slope, no evidence
        if self.beyond_range_passes:  # no surface there to graze: the ray went on
            # Only where every neighbour saw nothing either: a pixel on a silhouette may hold
            # a surface that the nearest-pixel projection of a point beside it misses.
            d[beyond & _all_neighbours(beyond)] = np.inf
        return d

    def add_frame(self, T_map_camera: np.ndarray, k: CameraIntrinsics, depth: np.ndarray,
                  covariance: np.ndarray | None = None) -> None:
        """Record one acquired frame (optical-frame pose in map, its intrinsics and depth)."""
        R = T_map_camera[:3, :3].T
        self._frames.append((R, -R @ T_map_camera[:3, 3], k, self.usable_depth(depth, k)))
        self._frustums.add(T_map_camera, k)

    def exposure_counts(self, points_map: np.ndarray, stop_at: int | None = None) -> np.ndarray:
        """n_ray(x): (N,) int32 frames whose ray passed through each point (class docstring);
        ``stop_at`` as in :meth:`ObservationGate.exposure_counts`. (:meth:`unsupported`, the
        support test and the shortcuts, are equation 4's own.)"""
        counts = np.zeros(len(points_map), dtype=np.int32)
        if len(points_map) == 0:
            return counts
        active = np.arange(len(points_map))
        p_all = np.asarray(points_map, dtype=np.float64)
        frames, meets, block = self._near(p_all)
        for f, meets_f in zip(frames, meets, strict=True):
            if stop_at is not None:
                active = active[counts[active] < stop_at]
            if len(active) == 0:
                break
            here = active[meets_f[block[active]]]
            counts[here[self._passed(f, p_all[here])]] += 1
        return counts

    def _passed(self, f: int, points: np.ndarray) -> np.ndarray:
        """Indices into ``points`` of those frame ``f``'s rays passed through."""
        R, t, k, d = self._frames[f]
        idx, v, u, z = pixels(points, R, t, k, self.min_range_m, self.max_range_m)
        return idx[d[v, u] >= z + self.margin_m]  # NaN (no usable return): False


class PoseGate(ObservationGate):
    """Equation 4 aware of the pose's uncertainty (the ``gated-pose`` condition).

    Each frame comes with its published pose's covariance (``sensor/pose_with_covariance``).
    With r = ``sigmas`` times the largest standard deviation of its position and a =
    ``sigmas`` times the largest of its rotation, a frame exposes a predicted point only when
    every pose within that ellipsoid would have had it in the frustum: its depth along the
    optical axis within ``[min_range + r, max_range - r]``, and its pixel at least
    ``f r / (z - r) + f tan(a)`` pixels inside the image's edges (how far a position error
    of r and a turn of a move the projection of a point z metres ahead). Support is searched
    within epsilon + r of the latest frame: the surface was placed with the poses' errors
    too. With zero covariance it is the frustum gate exactly.
    """

    def __init__(self, k: int, epsilon_m: float, min_range_m: float, max_range_m: float,
                 sigmas: float) -> None:
        if sigmas < 0:
            raise ValueError(f"the pose gate needs sigmas >= 0, got {sigmas}")
        super().__init__(k, epsilon_m, min_range_m, max_range_m)
        self.sigmas = sigmas
        self._reach: list[tuple[float, float]] = []  # per frame: (r in m, a in rad)

    def add_frame(self, T_map_camera: np.ndarray, intrinsics: CameraIntrinsics,
                  depth: np.ndarray, covariance: np.ndarray | None = None) -> None:
        cov = np.zeros((6, 6)) if covariance is None else np.asarray(covariance, np.float64)
        sd_pos = np.sqrt(max(np.linalg.eigvalsh(cov[:3, :3]).max(), 0.0))
        sd_rot = np.sqrt(max(np.linalg.eigvalsh(cov[3:, 3:]).max(), 0.0))
        self._reach.append((self.sigmas * sd_pos, min(self.sigmas * sd_rot, np.pi / 2 - 1e-6)))
        self.add_frustum(T_map_camera, intrinsics)

    @property
    def support_radius_m(self) -> float:
        return self.epsilon_m + (self._reach[-1][0] if self._reach else 0.0)

    def exposure_counts(self, points_map: np.ndarray, stop_at: int | None = None) -> np.ndarray:
        """Frames that expose each point under every pose of their uncertainty (class
        docstring); ``stop_at`` as in :meth:`ObservationGate.exposure_counts`."""
        counts = np.zeros(len(points_map), dtype=np.int32)
        if len(points_map) == 0:
            return counts
        active = np.arange(len(points_map))
        p_all = np.asarray(points_map, dtype=np.float64)
        frames, meets, block = self._near(p_all)  # a widened frustum lies inside the own
        for f, meets_f in zip(frames, meets, strict=True):
            R, t, k, (r, a) = (self._R_cam_map[f], self._t_cam_map[f], self._intrinsics[f],
                               self._reach[f])
            if stop_at is not None:
                active = active[counts[active] < stop_at]
            if len(active) == 0:
                break
            here = active[meets_f[block[active]]]
            pc = p_all[here] @ R.T + t
            z = pc[:, 2]
            ok = (z - r >= self.min_range_m) & (z + r <= self.max_range_m)
            zs = np.where(ok, z, 1.0)
            mu = k.fx * (r / np.maximum(zs - r, 1e-9) + np.tan(a))
            mv = k.fy * (r / np.maximum(zs - r, 1e-9) + np.tan(a))
            u = k.fx * pc[:, 0] / zs + k.cx
            v = k.fy * pc[:, 1] / zs + k.cy
            ok &= (u >= -0.5 + mu) & (u < k.width - 0.5 - mu)
            ok &= (v >= -0.5 + mv) & (v < k.height - 0.5 - mv)
            counts[here[ok]] += 1
        return counts


class SplitGate(RayGate):
    """Separate evidence for the planner's two uses of the map (the ``gated-split``
    condition).

    - Gain channel (what attracts the planner): a predicted point with no support within
      epsilon is withheld after K frames whose rays passed through it (:class:`RayGate`).
      Withholding it wrongly costs a view not taken.
    - Collision channel (what blocks it): withheld only when rays from two viewpoints at
      least ``baseline_m`` apart passed through it, with no support. Withholding it wrongly
      costs a collision, so the evidence must be free space seen from two places, not one
      viewpoint's rays, which a drifted pose or a repeated error could make consistent.

    With K = 2 (the default) the collision channel withholds a subset of what the gain
    channel does: a point may attract no longer and still block.
    """

    def __init__(self, k: int, epsilon_m: float, min_range_m: float, max_range_m: float,
                 margin_m: float, grazing_max_deg: float, baseline_m: float) -> None:
        if baseline_m < 0:
            raise ValueError(f"the split gate needs a baseline >= 0, got {baseline_m}")
        super().__init__(k, epsilon_m, min_range_m, max_range_m, margin_m, grazing_max_deg)
        self.baseline_m = baseline_m
        self._centres: list[np.ndarray] = []

    def add_frame(self, T_map_camera: np.ndarray, k: CameraIntrinsics, depth: np.ndarray,
                  covariance: np.ndarray | None = None) -> None:
        super().add_frame(T_map_camera, k, depth, covariance)
        self._centres.append(np.asarray(T_map_camera[:3, 3], dtype=np.float64))

    def seen_through_from_two_places(self, points_map: np.ndarray) -> np.ndarray:
        """(N,) bool: rays of two frames whose cameras were at least ``baseline_m`` apart
        passed through the point."""
        p = np.asarray(points_map, dtype=np.float64)
        passed = np.zeros((len(self._frames), len(p)), dtype=bool)
        if len(p):
            frames, meets, block = self._near(p)
            for f, meets_f in zip(frames, meets, strict=True):
                here = np.flatnonzero(meets_f[block])
                passed[f, here[self._passed(f, p[here])]] = True
        out = np.zeros(len(p), dtype=bool)
        centres = np.array(self._centres).reshape(-1, 3)
        for i in np.flatnonzero(passed.sum(axis=0) >= 2):
            c = centres[passed[:, i]]
            gaps = np.linalg.norm(c[:, None] - c[None], axis=2)
            out[i] = bool((gaps >= self.baseline_m).any())
        return out

    def withheld(self, points_map: np.ndarray, surface_map: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray]:
        """(N,) bool masks: withheld from the gain channel, and from the collision channel."""
        gain = np.zeros(len(points_map), dtype=bool)
        collision = np.zeros(len(points_map), dtype=bool)
        if len(points_map) == 0:
            return gain, collision
        # Equation 4's shortcut for both channels: supported points are in neither.
        candidates = np.flatnonzero(~self.supported(points_map, surface_map))
        unsupported = points_map[candidates]
        gain[candidates] = self.exposure_counts(unsupported, stop_at=self.k) >= self.k
        collision[candidates] = self.seen_through_from_two_places(unsupported)
        return gain, collision
