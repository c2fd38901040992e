"""The rover: kinematic SE(2) motion on the terrain, its limits, and true collisions.

The body's height, roll and pitch follow the terrain under its four wheels. Ground steeper than
the slope limit, or departing from the wheels' plane by more than the step limit anywhere under
the body, is untraversable: the rover stops before it, as a hazard-avoiding rover would.
Collisions are checked with FCL between the body (the box from ground clearance to body top)
and the scene's obstacle meshes, at every ``check_spacing_m`` along a motion, not only at
waypoints, and the smallest clearance of the motion is reported.
"""

from __future__ import annotations

from dataclasses import dataclass

import fcl
import numpy as np

from rover_sim.scene import Scene
from rovergate.config import RoverConfig
from rovergate.geometry import densify_se2, rot_x, rot_y, rot_z


@dataclass
class MotionResult:
    """Outcome of driving along a sequence of SE(2) poses."""

    final_xy_yaw: tuple[float, float, float]
    collided: bool
    collision_samples: int
    min_clearance_m: float
    length_m: float
    executed_fraction: float
    untraversable: bool = False
    contact: tuple[float, float, float] | None = None
    """Where the body first touched the scene (map frame), when it did."""


#: After a collision the rover stands back this far from the contact (or at its start).
STOP_MARGIN_M = 0.1


class RoverBody:
    """Terrain-following kinematics and FCL collision checks against the true obstacles."""

    def __init__(self, scene: Scene, rover: RoverConfig) -> None:
        self.scene = scene
        self.cfg = rover
        self._scene_obj = fcl.CollisionObject(mesh_bvh(scene.objects_mesh), fcl.Transform())
        h = rover.body_top_m - rover.clearance_m
        self._body = fcl.CollisionObject(fcl.Box(rover.length_m, rover.width_m, h))
        self._body_offset = np.array([0.0, 0.0, rover.clearance_m + h / 2])
        # Terrain checks: 3 x 5 points under the body (body frame), the wheels at its corners,
        # and the least-squares fit of a plane to the wheels' heights, computed once.
        self._under_u, self._under_v = np.meshgrid(
            np.array([-1.0, -0.5, 0.0, 0.5, 1.0]) * rover.length_m / 2,
            np.array([-1.0, 0.0, 1.0]) * rover.width_m / 2)
        wheels = np.c_[np.ones(4), self._under_u[[0, 0, 2, 2], [0, 4, 0, 4]],
                       self._under_v[[0, 0, 2, 2], [0, 4, 0, 4]]]
        self._wheel_fit = np.linalg.pinv(wheels)

    def start_state(self, x: float, y: float, yaw: float) -> tuple[float, float, float]:
        """The rover's state at a named start: the start itself."""
        return (x, y, yaw)

    def state_of(self, x: float, y: float, z: float, yaw: float, pitch: float
                 ) -> tuple[float, float, float]:
        """The state of a commanded pose: its place and heading (the terrain sets the rest)."""
        return (x, y, yaw)

    def clearance_at(self, state: tuple[float, ...]) -> float:
        """Distance between the body at ``state`` and the obstacles (<= 0: collision)."""
        return self.clearance(self.base_pose(*state))

    def base_pose(self, x: float, y: float, yaw: float) -> np.ndarray:
        """(4, 4) base pose on the terrain: wheels on the ground, roll and pitch from them."""
        half_l, half_w = self.cfg.length_m / 2, self.cfg.width_m / 2
        c, s = np.cos(yaw), np.sin(yaw)
        fwd, left = np.array([c, s]), np.array([-s, c])
        corners = np.array([[x, y] + a * half_l * fwd + b * half_w * left
                            for a, b in ((1, 1), (1, -1), (-1, 1), (-1, -1))])
        zs = self.scene.height_at(corners[:, 0], corners[:, 1])
        z = float(zs.mean())
        pitch = np.arctan2(((zs[0] + zs[1]) - (zs[2] + zs[3])) / 2, 2 * half_l)
        roll = np.arctan2(((zs[0] + zs[2]) - (zs[1] + zs[3])) / 2, 2 * half_w)
        R = rot_z(yaw) @ rot_y(-pitch) @ rot_x(roll)
        T = np.eye(4)
        T[:3, :3] = R
        T[:3, 3] = [x, y, z]
        return T

    def terrain_check(self, x: float, y: float, yaw: float) -> tuple[float, float]:
        """(slope_deg, step_m) of the ground under the body at (x, y, yaw).

        The slope is the tilt of the plane through the four wheel contacts; the step is the
        largest distance between the ground and that plane at 3 x 5 points under the body.
        """
        c, s = np.cos(yaw), np.sin(yaw)
        U, V = self._under_u, self._under_v
        Z = self.scene.height_at(x + c * U - s * V, y + s * U + c * V)
        coef = self._wheel_fit @ Z[[0, 0, 2, 2], [0, 4, 0, 4]]
        plane = coef[0] + coef[1] * U + coef[2] * V
        slope = float(np.degrees(np.arctan(np.hypot(coef[1], coef[2]))))
        return slope, float(np.abs(Z - plane).max())

    def traversable(self, x: float, y: float, yaw: float) -> bool:
        slope, step = self.terrain_check(x, y, yaw)
        return slope <= self.cfg.slope_limit_deg and step <= self.cfg.step_limit_m

    def clearance(self, T_map_base: np.ndarray) -> float:
        """Distance between the body box and the scene's obstacles (<= 0: collision)."""
        R = T_map_base[:3, :3]
        self._body.setTransform(fcl.Transform(R, T_map_base[:3, 3] + R @ self._body_offset))
        return clearance(self._body, self._scene_obj)

    def drive(self, start: tuple[float, float, float],
              waypoints: list[tuple[float, float, float]]) -> MotionResult:
        """Drive from ``start`` through ``waypoints`` (x, y, yaw), checking the whole motion.

        The rover stops at the last collision-free sample before the first collision, or before
        the first untraversable one (the start itself is not judged: the rover may leave it).
        """
        samples = densify_se2([start, *waypoints], self.cfg.check_spacing_m)
        total = _length(samples)
        clear = []
        min_clear = np.inf
        collided, n_collisions, blocked, contact = False, 0, False, None
        for k, pose in enumerate(samples):
            if k > 0 and not self.traversable(*pose):
                blocked = True
                break
            d = self.clearance(self.base_pose(*pose))
            min_clear = min(min_clear, d)
            if d <= 0.0:
                collided, n_collisions = True, n_collisions + 1
                contact = contact_point(self._body, self._scene_obj)
                break
            clear.append(d)
        stop = len(clear) - 1
        if collided:
            # The bumper halts the rover: it backs up along its motion to STOP_MARGIN_M from
            # what it touched (or to where it started), so that it can turn away next step.
            while stop > 0 and clear[stop] < STOP_MARGIN_M:
                stop -= 1
        last_free = samples[max(stop, 0)]
        driven = _length(samples[: max(stop, 0) + 1])
        return MotionResult(last_free, collided, n_collisions, float(min_clear), driven,
                            driven / total if total > 0 else 1.0, blocked, contact)


def mesh_bvh(mesh) -> fcl.BVHModel:
    """The FCL model of a trimesh mesh; an empty one (a scene without obstacles) is a
    far-away speck, which keeps FCL's model valid and touches nothing."""
    if len(mesh.faces) == 0:
        import trimesh
        mesh = trimesh.creation.box(extents=[1e-3] * 3)
        mesh.apply_translation([0.0, 0.0, -1e6])
    bvh = fcl.BVHModel()
    bvh.beginModel(len(mesh.vertices), len(mesh.faces))
    bvh.addSubModel(mesh.vertices, mesh.faces)
    bvh.endModel()
    return bvh


def clearance(body: fcl.CollisionObject, scene: fcl.CollisionObject) -> float:
    """Distance between two FCL objects, or -1 when they touch.

    FCL's distance query alone is not a collision test: for some shape pairs it returns a
    tiny positive number on contact, so contact is decided by its collision query.
    """
    data = fcl.CollisionData(request=fcl.CollisionRequest())
    if fcl.collide(body, scene, data.request, data.result):
        return -1.0
    return max(float(fcl.distance(body, scene, fcl.DistanceRequest(), fcl.DistanceResult())),
               0.0)


def contact_point(body: fcl.CollisionObject, scene: fcl.CollisionObject
                  ) -> tuple[float, float, float] | None:
    """A point where two touching FCL objects meet (FCL's first contact), or None."""
    request = fcl.CollisionRequest(num_max_contacts=1, enable_contact=True)
    result = fcl.CollisionResult()
    if not fcl.collide(body, scene, request, result) or not result.contacts:
        return None
    return tuple(float(v) for v in result.contacts[0].pos)


def _length(poses: list[tuple[float, float, float]]) -> float:
    xy = np.array([p[:2] for p in poses])
    return float(np.sum(np.linalg.norm(np.diff(xy, axis=0), axis=1))) if len(xy) > 1 else 0.0
