"""Any mesh file as a scene: OBJ, PLY, STL, GLB (whatever trimesh reads).

The file's mesh, turned so that its up axis is +z and scaled to metres, is the true geometry,
rendered and sampled as it is. What the rover drives on is the lowest surface under each point
(found by casting rays up from below through the mesh's upward-facing faces with pybullet,
on a 0.25 m grid, so that the file's faces must be wound consistently); faces lying on
that ground are ground, every other face is an obstacle. A mesh with no ground of its own (an
object, a building) is set on a flat plane at its lowest point, which becomes part of the
scene. The box of interest defaults to the mesh's footprint, cut to a square of at most
``region_m`` around its centre; the mesh is cropped 10 m beyond it (what is farther is not
drawn).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import trimesh
from scipy.ndimage import distance_transform_edt

from rover_sim.bullet import pb
from rover_sim.scene import Scene, heightfield_mesh
from rovergate.errors import ConfigError

GROUND_CELL_M = 0.25
GROUND_TOL_M = 0.08
CROP_MARGIN_M = 10.0
UP_AXES = ("x", "y", "z", "-x", "-y", "-z")


def _up_transform(up_axis: str) -> np.ndarray:
    if up_axis not in UP_AXES:
        raise ConfigError(
            f"--scene.up-axis {up_axis!r} is not an axis; use one of {', '.join(UP_AXES)}"
        )
    sign = -1.0 if up_axis.startswith("-") else 1.0
    axis = {"x": [1, 0, 0], "y": [0, 1, 0], "z": [0, 0, 1]}[up_axis[-1]]
    return trimesh.geometry.align_vectors(sign * np.array(axis, dtype=float), [0, 0, 1])


def read_mesh(path: Path, up_axis: str, scale: float) -> trimesh.Trimesh:
    """The file's triangles, z up, in metres; a bad file gives one line saying why."""
    path = Path(path)
    if not path.is_file():
        raise ConfigError(
            f"scene file {path} does not exist; pass a mesh file (OBJ, "
            "PLY, STL, GLB) or a scene name from `rovergate scenes`"
        )
    up = _up_transform(up_axis)
    if not scale > 0:
        raise ConfigError(f"--scene.scale {scale} must be positive (metres per unit)")
    try:
        mesh = trimesh.load(path, force="mesh", process=False)
    except Exception as exc:  # trimesh raises many kinds for unreadable files
        raise ConfigError(
            f"cannot read scene file {path} as a mesh ({exc}); export it "
            "as OBJ, PLY, STL or GLB"
        ) from None
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise ConfigError(
            f"scene file {path} holds no triangles; export the surface as a triangle mesh"
        )
    mesh = trimesh.Trimesh(
        np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces), process=False
    )
    mesh.apply_transform(up)
    mesh.apply_scale(scale)
    return mesh


def lowest_surface(mesh: trimesh.Trimesh, xs: np.ndarray, ys: np.ndarray) -> np.ndarray:
    """(ny, nx) height of the lowest upward-facing surface over each grid point (NaN where
    there is none). Downward-facing faces (the underside of a slab or a roof) are ignored, so
    a platform's ground is its top, not its bottom."""
    up = mesh.submesh([np.flatnonzero(mesh.face_normals[:, 2] > 0.05)], append=True)
    if len(up.faces) == 0:
        return np.full((len(ys), len(xs)), np.nan)
    cid = pb.connect(pb.DIRECT)
    try:
        shape = pb.createCollisionShape(
            pb.GEOM_MESH,
            vertices=up.vertices.tolist(),
            indices=up.faces.ravel().tolist(),
            flags=pb.GEOM_FORCE_CONCAVE_TRIMESH,
            physicsClientId=cid,
        )
        pb.createMultiBody(baseMass=0, baseCollisionShapeIndex=shape, physicsClientId=cid)
        X, Y = np.meshgrid(xs, ys)
        z0, z1 = mesh.bounds[0, 2] - 1.0, mesh.bounds[1, 2] + 1.0
        src = np.c_[X.ravel(), Y.ravel(), np.full(X.size, z0)]
        dst = np.c_[X.ravel(), Y.ravel(), np.full(X.size, z1)]
        Z = np.full(X.size, np.nan)
        batch = pb.MAX_RAY_INTERSECTION_BATCH_SIZE - 1
        for k in range(0, len(src), batch):
            hits = pb.rayTestBatch(
                src[k : k + batch].tolist(), dst[k : k + batch].tolist(), physicsClientId=cid
            )
            for i, h in enumerate(hits):
                if h[0] >= 0:
                    Z[k + i] = h[3][2]
    finally:
        pb.disconnect(cid)
    return Z.reshape(X.shape)


def load_mesh_scene(
    path: Path,
    up_axis: str = "z",
    scale: float = 1.0,
    region_m: float = 40.0,
    bounds_m: tuple[float, ...] | None = None,
    name: str | None = None,
) -> Scene:
    mesh = read_mesh(path, up_axis, scale)
    lo, hi = mesh.bounds
    if bounds_m is None:
        centre = (lo[:2] + hi[:2]) / 2
        half = np.minimum((hi[:2] - lo[:2]) / 2, region_m / 2)
        if np.any(half < 2 * 2.0 + 1.0):
            raise ConfigError(
                f"scene file {path} is only {hi[0] - lo[0]:.2f} x "
                f"{hi[1] - lo[1]:.2f} units across: too small for a rover; "
                "pass --scene.scale (metres per unit) or --scene.up-axis"
            )
        region = (
            centre[0] - half[0],
            centre[1] - half[1],
            centre[0] + half[0],
            centre[1] + half[1],
        )
    else:
        region = (bounds_m[0], bounds_m[1], bounds_m[3], bounds_m[4])
    # Crop what lies far outside the box of interest (it is never seen from inside); faces
    # are cut at the crop box, so that every vertex lies over the ground grid.
    for normal, x in (
        ([1, 0, 0], region[0] - CROP_MARGIN_M),
        ([-1, 0, 0], region[2] + CROP_MARGIN_M),
        ([0, 1, 0], region[1] - CROP_MARGIN_M),
        ([0, -1, 0], region[3] + CROP_MARGIN_M),
    ):
        origin = np.abs(normal) * x
        mesh = trimesh.intersections.slice_mesh_plane(mesh, np.array(normal, float), origin)
    if len(mesh.faces) == 0:
        raise ConfigError(
            f"scene file {path} has no triangles inside the box of "
            "interest; check --scene.bounds-m"
        )
    xs = np.arange(region[0] - CROP_MARGIN_M, region[2] + CROP_MARGIN_M + 1e-9, GROUND_CELL_M)
    ys = np.arange(region[1] - CROP_MARGIN_M, region[3] + CROP_MARGIN_M + 1e-9, GROUND_CELL_M)
    Z = lowest_surface(mesh, xs, ys)
    X, Y = np.meshgrid(xs, ys)
    in_roi = (region[0] <= X) & (region[2] >= X) & (region[1] <= Y) & (region[3] >= Y)
    missing = np.isnan(Z)
    if missing[in_roi].mean() > 0.5:
        # No ground of its own: stand it on a plane at its lowest point.
        Z = np.full(Z.shape, float(mesh.bounds[0, 2]))
        plane = heightfield_mesh(xs, ys, Z)
        mesh = trimesh.util.concatenate([mesh, plane])
    elif missing.any():  # holes in the ground: the nearest ground's height
        idx = distance_transform_edt(missing, return_distances=False, return_indices=True)
        Z = Z[tuple(idx)]

    scene = Scene(
        name or Path(path).stem,
        xs,
        ys,
        Z,
        [],
        (0, 0, 0, 0, 0, 0),
        mesh=mesh,
        description=f"mesh file {Path(path).name} (up {up_axis}, scale {scale:g})",
    )
    # A face is ground when it faces up and lies on the ground heightfield at its centre and
    # half-way to its corners (not at the corners: they sit on edges, where the heightfield
    # blends the step between a platform and what is below it).
    tri = mesh.triangles
    centre = tri.mean(axis=1, keepdims=True)
    probes = np.concatenate([centre, (tri + centre) / 2], axis=1).reshape(-1, 3)
    off = np.abs(probes[:, 2] - scene.height_at(probes[:, 0], probes[:, 1])).reshape(-1, 4)
    ground = (np.sum(off <= GROUND_TOL_M, axis=1) >= 3) & (mesh.face_normals[:, 2] > 0.05)
    v = mesh.vertices
    scene.objects = (
        [mesh.submesh([np.flatnonzero(~ground)], append=True)] if (~ground).any() else []
    )
    if bounds_m is not None:
        scene.bounds_m = tuple(float(b) for b in bounds_m)
    else:
        inside = (
            (v[:, 0] >= region[0])
            & (v[:, 0] <= region[2])
            & (v[:, 1] >= region[1])
            & (v[:, 1] <= region[3])
        )
        zs = np.r_[v[inside, 2], Z[in_roi]]
        scene.bounds_m = (
            region[0],
            region[1],
            float(zs.min()),
            region[2],
            region[3],
            float(zs.max()),
        )
    return scene
