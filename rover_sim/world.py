"""The pybullet world: the scene's meshes, the rover's body, and depth rendering.

pybullet runs in DIRECT mode (no window) and renders with its CPU TinyRenderer. The rover is
moved kinematically (its pose is set, no dynamics). Pixels that see the rover itself are
returned as NaN, like a real depth camera's self-filter. Two kinds of camera render: the
mast's (:class:`rovergate.config.SensorConfig`) and the rover's hazard cameras
(:class:`rovergate.config.HazcamConfig`), each with its own resolution, field and ranges.
"""

from __future__ import annotations

import atexit
import hashlib
import os
import shutil
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import trimesh

from rover_sim.bullet import pb
from rover_sim.scene import Scene
from rovergate.config import HazcamConfig, RoverConfig, SensorConfig
from rovergate.geometry import matrix_to_quat
from rovergate.types import CameraIntrinsics

NEAR_M = 0.05
EYE_NUDGE_M = np.array([1.13e-4, 0.71e-4, 0.37e-4])


_MESH_DIR: dict[int, Path] = {}


def _mesh_dir() -> Path:
    """This process's directory of scene meshes as OBJ files (removed when it exits; a
    process forked from it makes its own)."""
    pid = os.getpid()
    if pid not in _MESH_DIR:
        path = Path(tempfile.mkdtemp(prefix="rovergate-meshes-"))
        _MESH_DIR[pid] = path

        def remove() -> None:
            if os.getpid() == pid:
                shutil.rmtree(path, ignore_errors=True)
        atexit.register(remove)
    return _MESH_DIR[pid]


def mesh_file(vertices: np.ndarray, faces: np.ndarray) -> Path:
    """An OBJ file of the mesh (vertices to 17 significant digits, so that pybullet reads
    the same numbers it would from a list), written once per process and mesh."""
    vertices = np.ascontiguousarray(vertices, dtype=np.float64)
    faces = np.ascontiguousarray(faces, dtype=np.int64)
    digest = hashlib.sha256(vertices.tobytes() + faces.tobytes()).hexdigest()[:24]
    path = _mesh_dir() / f"{digest}.obj"
    if not path.exists():
        import trimesh
        text = trimesh.exchange.obj.export_obj(
            trimesh.Trimesh(vertices, faces, process=False), include_normals=False,
            include_color=False, include_texture=False, digits=17, header=None)
        tmp = path.with_suffix(f".tmp-{os.getpid()}")
        tmp.write_text(text)
        os.replace(tmp, path)
    return path


def add_scene(client: int, scene: Scene) -> None:
    """Put the scene's true geometry into a pybullet client, for rendering.

    Each mesh goes in as a file, not as lists: pybullet 3.2 keeps every vertex and index list
    it is given (and copies of an array) for as long as the process lives, some 4.5 MB a
    mission of the suite's scenes, which a study worker running hundreds of missions kept for
    good. Read from a file, the meshes render to the same depth, to the bit (a test checks)."""
    for mesh, rgba in scene.visual_meshes:
        for part in _pieces(mesh):
            vis = pb.createVisualShape(pb.GEOM_MESH,
                                       fileName=str(mesh_file(part.vertices, part.faces)),
                                       rgbaColor=rgba, physicsClientId=client)
            pb.createMultiBody(baseMass=0, baseVisualShapeIndex=vis, physicsClientId=client)


#: Faces per pybullet visual shape: pybullet takes at most 524,288 indices (three a face) in
#: one mesh and drops the rest, so a larger mesh (a long-traverse terrain, its hundreds of
#: rocks) goes in as several shapes. The suite's scenes are one shape each, as before.
MAX_SHAPE_FACES = 150_000


def _pieces(mesh: trimesh.Trimesh) -> list[trimesh.Trimesh]:
    """The mesh in consecutive runs of at most MAX_SHAPE_FACES faces, each with only the
    vertices its faces use (none when the mesh has no face)."""
    n = len(mesh.faces)
    if n <= MAX_SHAPE_FACES:
        return [mesh] if n else []
    out = []
    for lo in range(0, n, MAX_SHAPE_FACES):
        faces = np.asarray(mesh.faces[lo:lo + MAX_SHAPE_FACES])
        used, inverse = np.unique(faces, return_inverse=True)
        out.append(trimesh.Trimesh(np.asarray(mesh.vertices)[used], inverse.reshape(-1, 3),
                                   process=False))
    return out


@dataclass(frozen=True)
class DepthCamera:
    """What rendering needs of one camera: its image, its projection, its valid ranges."""

    intrinsics: CameraIntrinsics
    min_range_m: float
    max_range_m: float
    far_m: float
    projection: tuple

    @classmethod
    def of(cls, cfg: SensorConfig | HazcamConfig, client: int) -> DepthCamera:
        far = cfg.max_range_m * 1.5
        return cls(CameraIntrinsics.from_fov(cfg.width_px, cfg.height_px, cfg.vfov_deg),
                   cfg.min_range_m, cfg.max_range_m, far,
                   pb.computeProjectionMatrixFOV(fov=cfg.vfov_deg,
                                                 aspect=cfg.width_px / cfg.height_px,
                                                 nearVal=NEAR_M, farVal=far,
                                                 physicsClientId=client))


class PyBulletWorld:
    """Owns one pybullet client with the scene and the rover in it."""

    def __init__(self, scene: Scene, sensor: SensorConfig, rover: RoverConfig | None) -> None:
        """``rover`` None: no rover body in the world (the flyer is a bare camera)."""
        self.sensor = sensor
        self.client = pb.connect(pb.DIRECT)
        c = self.client
        self.rover_id = self.mast_id = -1
        add_scene(c, scene)
        self.mast = DepthCamera.of(sensor, c)
        self.intrinsics = self.mast.intrinsics
        if rover is not None:
            self._add_rover(sensor, rover)

    def _add_rover(self, sensor: SensorConfig, rover: RoverConfig) -> None:
        c = self.client
        body_h = rover.body_top_m - rover.clearance_m
        body = pb.createVisualShape(
            pb.GEOM_BOX, halfExtents=[rover.length_m / 2, rover.width_m / 2, body_h / 2],
            visualFramePosition=[0, 0, rover.clearance_m + body_h / 2],
            rgbaColor=[0.9, 0.9, 0.9, 1], physicsClientId=c)
        self.rover_id = pb.createMultiBody(baseMass=0, baseVisualShapeIndex=body,
                                           physicsClientId=c)
        mast_h = sensor.mast_height_m - rover.body_top_m
        mast = pb.createVisualShape(
            pb.GEOM_CYLINDER, radius=0.04, length=mast_h,
            visualFramePosition=[sensor.mast_forward_m, 0, rover.body_top_m + mast_h / 2],
            physicsClientId=c)
        self.mast_id = pb.createMultiBody(baseMass=0, baseVisualShapeIndex=mast,
                                          physicsClientId=c)

    def set_rover_pose(self, T_map_base: np.ndarray) -> None:
        if self.rover_id < 0:
            return
        q = matrix_to_quat(T_map_base[:3, :3])
        for body in (self.rover_id, self.mast_id):
            pb.resetBasePositionAndOrientation(body, T_map_base[:3, 3].tolist(), q.tolist(),
                                               physicsClientId=self.client)

    def render_depth(self, T_map_camera: np.ndarray, camera: DepthCamera | None = None
                     ) -> np.ndarray:
        """(H, W) float32 z-depth in metres from the optical frame pose of ``camera`` (the
        mast's by default); +Inf where nothing is within range, NaN where the return is
        invalid."""
        cam = camera or self.mast
        k = cam.intrinsics
        # TinyRenderer never returns when a triangle's plane passes exactly through the eye
        # (an axis-aligned face and an eye on the same round coordinate): move the eye by a
        # tenth of a millimetre in an odd direction, which no scene lines up with.
        eye = T_map_camera[:3, 3] + EYE_NUDGE_M
        forward, down = T_map_camera[:3, 2], T_map_camera[:3, 1]
        view = pb.computeViewMatrix(eye.tolist(), (eye + forward).tolist(), (-down).tolist(),
                                    physicsClientId=self.client)
        _, _, _, zbuf, seg = pb.getCameraImage(
            k.width, k.height, view, cam.projection, renderer=pb.ER_TINY_RENDERER,
            physicsClientId=self.client)
        zbuf = np.asarray(zbuf, dtype=np.float64).reshape(k.height, k.width)
        seg = np.asarray(seg).reshape(k.height, k.width)
        far = cam.far_m
        depth = far * NEAR_M / (far - (far - NEAR_M) * zbuf)
        # REP 117: +Inf where nothing is within the maximum range (the ray passed through all
        # of it), NaN where there is no valid return (too near, or the rover's own body).
        nothing = (zbuf >= 1.0 - 1e-7) | (depth > cam.max_range_m)
        invalid = depth < cam.min_range_m
        if self.rover_id >= 0:
            invalid |= (seg == self.rover_id) | (seg == self.mast_id)
        depth = np.where(nothing, np.inf, depth)
        return np.where(invalid, np.nan, depth).astype(np.float32)

    def close(self) -> None:
        if pb.isConnected(self.client):
            pb.disconnect(self.client)
