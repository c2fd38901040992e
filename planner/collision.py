"""Collision checking of the rover body against the planner-facing occupancy, with FCL.

The map is a point set, so the ground itself is made of points. The model first estimates the
ground: the lowest map point in each ``ground_cell_m`` cell, then the lowest over the rover's
footprint around it. A map point is an obstacle when it stands between the body's clearance
and its top above that ground (overhangs higher than the body are passed under; pebbles lower
than the clearance are driven over). Each obstacle point becomes a small box in an FCL
broad-phase manager; the rover is the box of its body, placed on the estimated ground.

Everything reads the same planner-facing map as the gain: a hallucinated point both attracts
the rover and blocks its way, as in the paper.
"""

from __future__ import annotations

import fcl
import numpy as np
from scipy.ndimage import minimum_filter

from rovergate.config import RoverConfig


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

    def is_free(self, x: float, y: float, yaw: float) -> bool:
        """Whether the body at (x, y, yaw) on the estimated ground touches no obstacle point."""
        self.checks += 1
        if not self._objects:
            return True
        c, s = np.cos(yaw), np.sin(yaw)
        R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        self._body.setTransform(fcl.Transform(R, [x, y, self.ground_z(x, y) + self._body_dz]))
        data = fcl.CollisionData(request=fcl.CollisionRequest())
        self._manager.collide(self._body, data, fcl.defaultCollisionCallback)
        return not data.result.is_collision
