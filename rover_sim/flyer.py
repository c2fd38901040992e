"""The flyer: a free-flying camera (the paper's benchmark platform) and its true collisions.

Its state is (x, y, z, yaw, pitch): a position and a view direction; the body is a sphere
that must stay clear of all true geometry, ground included. Motion is checked with FCL every
``check_spacing_m`` along the straight segments between waypoints, as the rover's is.
"""

from __future__ import annotations

import fcl
import numpy as np

from rover_sim.rover import STOP_MARGIN_M, MotionResult, clearance, contact_point, mesh_bvh
from rover_sim.scene import Scene
from rovergate.config import FlyerConfig
from rovergate.types import Pose

FlyerState = tuple[float, float, float, float, float]


def scene_bvh(scene: Scene) -> fcl.BVHModel:
    """The FCL model of the scene's solid mesh, built once per scene (it is only read)."""
    bvh = getattr(scene, "_fcl_bvh", None)
    if bvh is None:
        bvh = scene._fcl_bvh = mesh_bvh(scene.solid_mesh)
    return bvh


class FlyerBody:
    """Sphere kinematics and FCL clearance against the whole true scene."""

    def __init__(self, scene: Scene, flyer: FlyerConfig, check_spacing_m: float) -> None:
        self.scene = scene
        self.cfg = flyer
        self.spacing = check_spacing_m
        self._scene_obj = fcl.CollisionObject(scene_bvh(scene), fcl.Transform())
        self._sphere = fcl.CollisionObject(fcl.Sphere(flyer.radius_m))

    def start_state(self, x: float, y: float, yaw: float) -> FlyerState:
        """The flyer's start above a named (ground) start, looking level along ``yaw``."""
        return (x, y, float(self.scene.height_at(x, y)) + self.cfg.altitude_m, yaw, 0.0)

    @staticmethod
    def state_of(x: float, y: float, z: float, yaw: float, pitch: float) -> FlyerState:
        """The state of a commanded pose: all of it."""
        return (x, y, z, yaw, pitch)

    def clearance_at(self, state: tuple[float, ...]) -> float:
        """Distance between the sphere at ``state`` and the scene (<= 0: collision)."""
        return self.clearance(state[:3])

    @staticmethod
    def base_pose(x: float, y: float, z: float, yaw: float, pitch: float) -> np.ndarray:
        return Pose.from_xyz_yaw_pitch(x, y, z, yaw, pitch).matrix()

    def clearance(self, xyz) -> float:
        """Distance between the sphere at ``xyz`` and the scene (<= 0: collision)."""
        self._sphere.setTransform(fcl.Transform(np.asarray(xyz, dtype=np.float64)))
        return clearance(self._sphere, self._scene_obj)

    def drive(self, start: FlyerState, waypoints: list[FlyerState]) -> MotionResult:
        """Fly from ``start`` through ``waypoints``; stops before the first collision."""
        states = [start, *waypoints]
        samples = [states[0]]
        for a, b in zip(states[:-1], states[1:], strict=True):
            n = max(1, int(np.ceil(np.linalg.norm(np.subtract(b[:3], a[:3])) / self.spacing)))
            dyaw = (b[3] - a[3] + np.pi) % (2 * np.pi) - np.pi
            for k in range(1, n + 1):
                f = k / n
                p = [a[i] + f * (b[i] - a[i]) for i in range(3)]
                samples.append((*p, a[3] + f * dyaw, a[4] + f * (b[4] - a[4])))
        clear, min_clear, collided, hits, contact = [], np.inf, False, 0, None
        for s in samples:
            d = self.clearance(s[:3])
            min_clear = min(min_clear, d)
            if d <= 0.0:
                collided, hits = True, 1
                contact = contact_point(self._sphere, self._scene_obj)
                break
            clear.append(d)
        last = len(clear) - 1
        while collided and last > 0 and clear[last] < STOP_MARGIN_M:
            last -= 1  # halt STOP_MARGIN_M short of the contact, as the rover does
        last = max(last, 0)
        xyz = np.array([s[:3] for s in samples])
        seg = np.linalg.norm(np.diff(xyz, axis=0), axis=1)
        total, driven = float(seg.sum()), float(seg[:last].sum())
        final = samples[last]
        final = (*final[:3], float((final[3] + np.pi) % (2 * np.pi) - np.pi), final[4])
        return MotionResult(final, collided, hits, float(min_clear), driven,
                            driven / total if total > 0 else 1.0, contact=contact)
