"""Degraded sensing: range-proportional depth noise, structured dropout, and pose drift.

Everything is off by default and seeded from the mission seed and the step, so a degraded run
is as reproducible as a clean one, in one process or many.

- Noise: z-depth plus a Gaussian with standard deviation ``noise_frac`` times the range.
- Dropout: missing returns become NaN, independently per pixel (``dropout_pixel_prob``), in
  blobs (``dropout_blob_frac`` of each image: the top quantile of a smoothed random field, so
  blobs have a size of about ``dropout_blob_px``), and where the surface is seen at an
  incidence angle above ``grazing_max_deg``.
- Drift: a random walk on the pose the platform publishes (x, y, z and heading, one step of
  the walk per planning step). The depth is rendered from the true pose, ground truth uses the
  true pose, and commands given in the drifted frame are carried out relative to the true one,
  as a rover that trusts its own odometry would.
"""

from __future__ import annotations

import numpy as np

from rovergate.config import SensingConfig
from rovergate.geometry import rot_z
from rovergate.types import CameraIntrinsics

_DEPTH_STREAM, _DRIFT_STREAM = 0xD0, 0xD1
#: The hazard cameras' own streams (front, rear): their noise and dropout are drawn apart
#: from the mast's, so adding them changes no draw of the mast camera.
HAZCAM_STREAMS = {"front": 0xE0, "rear": 0xE1}


def incidence_cos(depth: np.ndarray, k: CameraIntrinsics) -> np.ndarray:
    """(H, W) |cos| of the angle between each pixel's ray and the surface normal (NaN where
    the normal is unknown: no return at the pixel or its neighbours)."""
    h, w = depth.shape
    u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    z = np.where(np.isfinite(depth), depth, np.nan).astype(np.float64)  # +Inf: no surface
    P = np.stack([(u - k.cx) / k.fx * z, (v - k.cy) / k.fy * z, z], axis=-1)
    du = np.gradient(P, axis=1)
    dv = np.gradient(P, axis=0)
    n = np.cross(du, dv)
    with np.errstate(invalid="ignore", divide="ignore"):
        n /= np.linalg.norm(n, axis=-1, keepdims=True)
        ray = P / np.linalg.norm(P, axis=-1, keepdims=True)
        return np.abs(np.sum(n * ray, axis=-1))


class Sensing:
    """Applies the configured degradations of one mission."""

    def __init__(self, cfg: SensingConfig, seed: int) -> None:
        self.cfg = cfg
        self.seed = int(seed)
        self._walk = [np.zeros(4)]  # cumulative (dx, dy, dz, dyaw) at steps 0, 1, ...

    @property
    def degrades_depth(self) -> bool:
        c = self.cfg
        return (c.noise_frac > 0 or c.dropout_pixel_prob > 0 or c.dropout_blob_frac > 0
                or c.grazing_max_deg < 90)

    def dropout_mask(self, shape: tuple[int, int], rng: np.random.Generator) -> np.ndarray:
        """(H, W) bool: the pixels whose return is lost (blobs and independent pixels)."""
        c = self.cfg
        lost = np.zeros(shape, dtype=bool)
        if c.dropout_blob_frac > 0:
            from scipy.ndimage import gaussian_filter  # (degraded sensing only: 0.25 s)
            field = gaussian_filter(rng.standard_normal(shape), sigma=c.dropout_blob_px,
                                    mode="wrap")
            lost |= field > np.quantile(field, 1.0 - c.dropout_blob_frac)
        if c.dropout_pixel_prob > 0:
            lost |= rng.random(shape) < c.dropout_pixel_prob
        return lost

    def degrade(self, depth: np.ndarray, k: CameraIntrinsics, step: int,
                stream: int = _DEPTH_STREAM) -> np.ndarray:
        """The depth image as the degraded sensor returns it (a new array); ``stream`` keeps
        each camera's draws apart (:data:`HAZCAM_STREAMS`)."""
        if not self.degrades_depth:
            return depth
        c = self.cfg
        rng = np.random.default_rng([self.seed, step, stream])
        out = depth.astype(np.float32).copy()
        if c.grazing_max_deg < 90:
            cos = incidence_cos(depth, k)
            out[np.nan_to_num(cos, nan=1.0) < np.cos(np.radians(c.grazing_max_deg))] = np.nan
        if c.noise_frac > 0:
            noise = rng.standard_normal(out.shape).astype(np.float32)
            out += noise * np.float32(c.noise_frac) * np.where(np.isfinite(depth), depth, 0)
        out[self.dropout_mask(out.shape, rng)] = np.nan
        return out

    def drift_at(self, step: int) -> np.ndarray:
        """(4,) cumulative drift (dx, dy, dz, dyaw in radians) at ``step``."""
        c = self.cfg
        sd = np.array([c.drift_xy_m, c.drift_xy_m, c.drift_z_m, np.radians(c.drift_yaw_deg)])
        while len(self._walk) <= step:
            t = len(self._walk)
            inc = np.random.default_rng([self.seed, t, _DRIFT_STREAM]).standard_normal(4) * sd
            self._walk.append(self._walk[-1] + inc)
        return self._walk[step]

    def pose_covariance(self, step: int, lever_m: float = 0.0) -> np.ndarray:
        """(6, 6) covariance of a published pose at ``step`` (x, y, z, rotation about x, y,
        z; ROS order), as the drift model states it: ``step`` independent increments of the
        random walk, and the heading error's effect on a point ``lever_m`` from the base
        (the camera on its mast) added to x and y, which bounds it in every direction. What
        an onboard estimator would report; the drift drawn is not in it."""
        c = self.cfg
        yaw_var = step * np.radians(c.drift_yaw_deg) ** 2
        cov = np.zeros((6, 6))
        cov[0, 0] = cov[1, 1] = step * c.drift_xy_m ** 2 + lever_m ** 2 * yaw_var
        cov[2, 2] = step * c.drift_z_m ** 2
        cov[5, 5] = yaw_var
        return cov

    def drift_transform(self, T_true_base: np.ndarray, step: int) -> np.ndarray:
        """(4, 4) D with published pose = D @ true pose: the platform believes it is shifted by
        the drift and turned by its heading error about its own position."""
        d = self.drift_at(step)
        if not d.any():
            return np.eye(4)
        T_pub = T_true_base.copy()
        T_pub[:3, :3] = rot_z(d[3]) @ T_true_base[:3, :3]
        T_pub[:3, 3] = T_true_base[:3, 3] + d[:3]
        return T_pub @ np.linalg.inv(T_true_base)
