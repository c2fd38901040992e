"""The observation-gated filter (paper, equation 4).

A predicted point x is *unsupported* at step t when it has been inside at least K acquired
camera frustums, n_t(x) >= K, and no observed surface point lies within epsilon of it:

    U_t = { x in O_hat_t : n_t(x) >= K  and  min_{p in S_t} ||x - p|| > epsilon }

The planner then receives S_t together with O_hat_t minus U_t. U_t is recomputed from scratch
every step over the current prediction and all frustums so far, so later surface support
near a point restores it. Frustum inclusion is the paper's exposure proxy: inside the image,
in front of the camera, between the sensor's minimum and maximum range. It ignores occlusion.
"""

from __future__ import annotations

import numpy as np

from gate.views import pixels
from rovergate.spatial import kdtree
from rovergate.types import CameraIntrinsics

_CHUNK_FRUSTUMS = 16


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

    @property
    def n_frustums(self) -> int:
        return len(self._R_cam_map)

    def add_frustum(self, T_map_camera: np.ndarray, intrinsics: CameraIntrinsics) -> None:
        """Record the frustum of one acquired frame (optical-frame pose in map)."""
        R = T_map_camera[:3, :3].T
        self._R_cam_map.append(R)
        self._t_cam_map.append(-R @ T_map_camera[:3, 3])
        self._intrinsics.append(intrinsics)

    def add_frame(self, T_map_camera: np.ndarray, intrinsics: CameraIntrinsics,
                  depth: np.ndarray) -> None:
        """Record an acquired frame: its frustum (the frustum gate does not read depth)."""
        self.add_frustum(T_map_camera, intrinsics)

    def exposure_counts(self, points_map: np.ndarray, stop_at: int | None = None) -> np.ndarray:
        """n_t(x): (N,) int32 number of recorded frustums that contain each point.

        ``stop_at``: a point's count may stop growing once it reaches this many (only whether
        n_t >= K matters to the filter), which lets the count skip it in later frustums."""
        counts = np.zeros(len(points_map), dtype=np.int32)
        if len(points_map) == 0 or not self._R_cam_map:
            return counts
        active = np.arange(len(points_map))
        for lo in range(0, self.n_frustums, _CHUNK_FRUSTUMS):
            if stop_at is not None:
                active = active[counts[active] < stop_at]
                if len(active) == 0:
                    break
            p = points_map[active].astype(np.float64)
            R = np.stack(self._R_cam_map[lo:lo + _CHUNK_FRUSTUMS])     # (F, 3, 3)
            t = np.stack(self._t_cam_map[lo:lo + _CHUNK_FRUSTUMS])     # (F, 3)
            ks = self._intrinsics[lo:lo + _CHUNK_FRUSTUMS]
            pc = np.einsum("fij,nj->fni", R, p) + t[:, None, :]          # (F, N, 3)
            z = pc[..., 2]
            in_range = (z >= self.min_range_m) & (z <= self.max_range_m)
            zs = np.where(in_range, z, 1.0)
            fx = np.array([k.fx for k in ks])[:, None]
            fy = np.array([k.fy for k in ks])[:, None]
            cx = np.array([k.cx for k in ks])[:, None]
            cy = np.array([k.cy for k in ks])[:, None]
            w = np.array([k.width for k in ks])[:, None]
            h = np.array([k.height for k in ks])[:, None]
            u = fx * pc[..., 0] / zs + cx
            v = fy * pc[..., 1] / zs + cy
            inside = in_range & (u >= -0.5) & (u < w - 0.5) & (v >= -0.5) & (v < h - 0.5)
            counts[active] += inside.sum(axis=0, dtype=np.int32)
        return counts

    def support_distance(self, points_map: np.ndarray, surface_map: np.ndarray) -> np.ndarray:
        """(N,) distance from each point to the nearest observed surface point (inf if none
        within epsilon: only the comparison with epsilon matters)."""
        if len(surface_map) == 0:
            return np.full(len(points_map), np.inf)
        d, _ = kdtree(surface_map).query(points_map, k=1, distance_upper_bound=self.epsilon_m)
        return d

    def unsupported(self, points_map: np.ndarray, surface_map: np.ndarray) -> np.ndarray:
        """(N,) bool mask of U_t: exposed at least K times with no support within epsilon."""
        if len(points_map) == 0:
            return np.zeros(0, dtype=bool)
        # Supported points are never in U_t: count exposures only for the others.
        out = self.support_distance(points_map, surface_map) > self.epsilon_m
        candidates = np.flatnonzero(out)
        out[candidates] = self.exposure_counts(points_map[candidates], stop_at=self.k) >= self.k
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

        U_t = { x in O_hat_t : n_ray(x) >= K  and  min_{p in S_t} ||x - p|| > epsilon }
    """

    def __init__(self, k: int, epsilon_m: float, min_range_m: float, max_range_m: float,
                 margin_m: float, grazing_max_deg: float) -> None:
        if k < 1 or epsilon_m <= 0 or margin_m < 0 or not 0 < grazing_max_deg <= 90:
            raise ValueError(f"the ray gate needs k >= 1, epsilon > 0, margin >= 0 and a "
                             f"grazing angle in (0, 90]; got k={k}, epsilon={epsilon_m}, "
                             f"margin={margin_m}, angle={grazing_max_deg}")
        super().__init__(k, epsilon_m, min_range_m, max_range_m)
        self.margin_m = margin_m
        self.tan_grazing = np.inf if grazing_max_deg >= 90 else np.tan(np.radians(grazing_max_deg))
        self._frames: list[tuple[np.ndarray, np.ndarray, CameraIntrinsics, np.ndarray]] = []

    @property
    def n_frustums(self) -> int:
        return len(self._frames)

    def usable_depth(self, depth: np.ndarray, k: CameraIntrinsics) -> np.ndarray:
        """The depth image with every unusable return (dropped, saturated, grazing) NaN."""
        d = np.asarray(depth, dtype=np.float32).copy()
        d[~np.isfinite(d)] = np.nan
        if np.isfinite(self.tan_grazing):
            with np.errstate(invalid="ignore"):
                gv, gu = np.gradient(d.astype(np.float64))
                tan = np.hypot(gu * k.fx, gv * k.fy) / d
            d[~(tan <= self.tan_grazing)] = np.nan  # NaN neighbours: no slope, no evidence
        return d

    def add_frame(self, T_map_camera: np.ndarray, k: CameraIntrinsics, depth: np.ndarray
                  ) -> None:
        """Record one acquired frame (optical-frame pose in map, its intrinsics and depth)."""
        R = T_map_camera[:3, :3].T
        self._frames.append((R, -R @ T_map_camera[:3, 3], k, self.usable_depth(depth, k)))

    def exposure_counts(self, points_map: np.ndarray, stop_at: int | None = None) -> np.ndarray:
        """n_ray(x): (N,) int32 frames whose ray passed through each point (class docstring);
        ``stop_at`` as in :meth:`ObservationGate.exposure_counts`. (:meth:`unsupported`, the
        support test and the shortcuts, are equation 4's own.)"""
        counts = np.zeros(len(points_map), dtype=np.int32)
        active = np.arange(len(points_map))
        p_all = np.asarray(points_map, dtype=np.float64)
        for R, t, k, d in self._frames:
            if stop_at is not None:
                active = active[counts[active] < stop_at]
            if len(active) == 0:
                break
            idx, v, u, z = pixels(p_all[active], R, t, k, self.min_range_m, self.max_range_m)
            passed = d[v, u] >= z + self.margin_m  # NaN (no usable return): False
            counts[active[idx[passed]]] += 1
        return counts
