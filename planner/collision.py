"""Collision checking of the rover body against the planner-facing occupancy, with FCL.

The map is a point set, so the ground itself is made of points. The model first estimates the
ground: the lowest map point in each ``ground_cell_m`` cell, then the lowest over the rover's
footprint around it. A map point is an obstacle when it stands between the body's clearance
and its top above that ground (overhangs higher than the body are passed under; pebbles lower
than the clearance are driven over). Each obstacle point becomes a small box in an FCL
broad-phase manager; the rover is the box of its body, placed on the estimated ground.

The rover's limits are checked on the same estimate: the plane through the ground under its
four wheels must be no steeper than the slope limit, and the lowest map point of each cell under
the body no farther from that plane than the step limit (cells without points are unknown and
pass). The flyer's model (:class:`FlyerCollisionModel`) keeps its sphere clear of every map
point and between its altitude limits over the estimated ground.

Everything reads the same planner-facing map as the gain: a hallucinated point both attracts
the platform and blocks its way, as in the paper.
"""

from __future__ import annotations

import fcl
import numpy as np
from scipy.ndimage import minimum_filter
from scipy.spatial import cKDTree

from rovergate.config import FlyerConfig, RoverConfig


class OccupancyCollisionModel:
    """FCL model of one step's planner-facing occupancy."""

    def __init__(self, points_map: np.ndarray, rover: RoverConfig, bounds_m: tuple[float, ...],
                 ground_cell_m: float, obstacle_voxel_m: float, fallback_ground_z: float) -> None:
        self.rover = rover
        self.cell = ground_cell_m
        self.fallback_ground_z = fallback_ground_z
        xmin, ymin, _, xmax, ymax, _ = bounds_m
        margin = 5.0
        self.origin = np.array([xmin - margin, ymin - margin])
        self.shape = (int(np.ceil((ymax - ymin + 2 * margin) / ground_cell_m)) + 1,
                      int(np.ceil((xmax - xmin + 2 * margin) / ground_cell_m)) + 1)
        grid = np.full(self.shape, np.inf)
        ij = self._cells(points_map[:, :2]) if len(points_map) else np.zeros((0, 2), int)
        inside = ((ij[:, 0] >= 0) & (ij[:, 0] < self.shape[0]) & (ij[:, 1] >= 0)
                  & (ij[:, 1] < self.shape[1]))
        np.minimum.at(grid, (ij[inside, 0], ij[inside, 1]), points_map[inside, 2])
        half_diag = np.hypot(rover.length_m, rover.width_m) / 2
        size = 2 * int(np.ceil(half_diag / ground_cell_m)) + 1
        self.raw_ground = grid
        self.ground = minimum_filter(grid, size=size, mode="nearest")

        h = points_map[inside, 2] - self.ground[ij[inside, 0], ij[inside, 1]]
        obstacle = (h > rover.clearance_m) & (h < rover.body_top_m)
        self.obstacle_points = points_map[inside][obstacle]
        edge = obstacle_voxel_m
        self._objects = [fcl.CollisionObject(fcl.Box(edge, edge, edge), fcl.Transform(p))
                         for p in self.obstacle_points.astype(np.float64)]
        self._manager = fcl.DynamicAABBTreeCollisionManager()
        if self._objects:
            self._manager.registerObjects(self._objects)
        self._manager.setup()
        body_h = rover.body_top_m - rover.clearance_m
        self._body = fcl.CollisionObject(fcl.Box(rover.length_m, rover.width_m, body_h))
        self._body_dz = rover.clearance_m + body_h / 2
        self.checks = 0

    def _cells(self, xy: np.ndarray) -> np.ndarray:
        ij = np.floor((xy - self.origin) / self.cell).astype(np.int64)
        return ij[:, ::-1]  # (row = y, col = x)

    def ground_z(self, x: float, y: float) -> float:
        """Estimated ground height under (x, y); the fallback where the map has no points."""
        i, j = self._cells(np.array([[x, y]]))[0]
        if 0 <= i < self.shape[0] and 0 <= j < self.shape[1] and np.isfinite(self.ground[i, j]):
            return float(self.ground[i, j])
        return self.fallback_ground_z

    def traversable(self, x: float, y: float, yaw: float) -> bool:
        """Whether the estimated ground under the body is within the slope and step limits."""
        c, s = np.cos(yaw), np.sin(yaw)
        u = np.array([-1.0, -0.5, 0.0, 0.5, 1.0]) * self.rover.length_m / 2
        v = np.array([-1.0, 0.0, 1.0]) * self.rover.width_m / 2
        U, V = np.meshgrid(u, v)
        ij = self._cells(np.c_[(x + c * U - s * V).ravel(), (y + s * U + c * V).ravel()])
        inside = ((ij[:, 0] >= 0) & (ij[:, 0] < self.shape[0]) & (ij[:, 1] >= 0)
                  & (ij[:, 1] < self.shape[1]))
        if not inside.all():
            return True
        Z = self.raw_ground[ij[:, 0], ij[:, 1]].reshape(U.shape)
        corners = Z[[0, 0, 2, 2], [0, 4, 0, 4]]
        known = np.isfinite(corners)
        if known.sum() >= 3:
            A = np.c_[np.ones(4), U[[0, 0, 2, 2], [0, 4, 0, 4]], V[[0, 0, 2, 2], [0, 4, 0, 4]]]
            coef = np.linalg.lstsq(A[known], corners[known], rcond=None)[0]
            if np.degrees(np.arctan(np.hypot(coef[1], coef[2]))) > self.rover.slope_limit_deg:
                return False
            plane = coef[0] + coef[1] * U + coef[2] * V
            below = np.isfinite(Z)
            if np.any(np.abs(Z[below] - plane[below]) > self.rover.step_limit_m):
                return False
        return True

    def is_free(self, x: float, y: float, yaw: float) -> bool:
        """Whether the body at (x, y, yaw) on the estimated ground touches no obstacle point
        and stands within the rover's slope and step limits."""
        self.checks += 1
        if not self.traversable(x, y, yaw):
            return False
        if not self._objects:
            return True
        c, s = np.cos(yaw), np.sin(yaw)
        R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        self._body.setTransform(fcl.Transform(R, [x, y, self.ground_z(x, y) + self._body_dz]))
        data = fcl.CollisionData(request=fcl.CollisionRequest())
        self._manager.collide(self._body, data, fcl.defaultCollisionCallback)
        return not data.result.is_collision


class FlyerCollisionModel:
    """The flyer's check on one step's planner-facing occupancy: a sphere among points."""

    def __init__(self, points_map: np.ndarray, flyer: FlyerConfig, ground: OccupancyCollisionModel,
                 margin_m: float = 0.1) -> None:
        self.cfg = flyer
        self.ground = ground
        self.reach = flyer.radius_m + margin_m
        self._tree = cKDTree(points_map) if len(points_map) else None
        self.checks = 0

    def altitude_band(self, x: float, y: float) -> tuple[float, float]:
        g = self.ground.ground_z(x, y)
        return g + self.cfg.min_altitude_m, g + self.cfg.max_altitude_m

    def is_free(self, x: float, y: float, z: float) -> bool:
        """No map point within the sphere (plus a margin), and inside the altitude band."""
        self.checks += 1
        lo, hi = self.altitude_band(x, y)
        if not lo <= z <= hi:
            return False
        if self._tree is None:
            return True
        d, _ = self._tree.query((x, y, z), distance_upper_bound=self.reach)
        return not np.isfinite(d)
