"""A scene: the true geometry of one world (ground truth lives in ``rover_sim`` only).

A :class:`Scene` holds the geometry, its box of interest, its ``d_scene`` (the diagonal of that
box, which every tolerance scales with) and its named starts. The suite's procedural scenes are
in :mod:`rover_sim.suite`, mesh files in :mod:`rover_sim.mesh_scene`, the registry and the
start selection in :mod:`rover_sim.catalog`.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import trimesh

from rovergate.geometry import in_region


@dataclass
class Scene:
    """True geometry and metadata of one world.

    Procedural scenes are a terrain heightfield plus convex obstacle meshes. Mesh scenes (a
    file) keep the file's mesh whole as the true geometry (``mesh``); their heightfield is the
    lowest surface under each point, which the rover drives on, and their obstacles are the
    faces that are not that ground.
    """

    name: str
    terrain_xs: np.ndarray
    """(nx,) grid x coordinates of the ground heightfield."""
    terrain_ys: np.ndarray
    """(ny,) grid y coordinates."""
    terrain_z: np.ndarray
    """(ny, nx) heights; the terrain mesh interpolates them linearly over triangles."""
    objects: list[trimesh.Trimesh]
    """Obstacle meshes (rocks, structures), in map coordinates; convex in procedural scenes."""
    bounds_m: tuple[float, float, float, float, float, float]
    """Box of interest (xmin, ymin, zmin, xmax, ymax, zmax): coverage counts what is inside."""
    starts: dict[str, tuple[float, float, float]] = field(default_factory=dict)
    """Named starts: rover base (x, y, yaw); the flyer starts above them."""
    mesh: trimesh.Trimesh | None = None
    """Mesh scenes: the whole true geometry (rendered and sampled as it is)."""
    description: str = ""
    """One line: what the scene is and what it stresses."""

    @property
    def d_scene_m(self) -> float:
        lo, hi = np.array(self.bounds_m[:3]), np.array(self.bounds_m[3:])
        return float(np.linalg.norm(hi - lo))

    @property
    def terrain(self) -> trimesh.Trimesh:
        return heightfield_mesh(self.terrain_xs, self.terrain_ys, self.terrain_z)

    @property
    def objects_mesh(self) -> trimesh.Trimesh:
        if not self.objects:
            return trimesh.Trimesh(np.zeros((0, 3)), np.zeros((0, 3), int))
        return trimesh.util.concatenate(self.objects)

    @property
    def visual_meshes(self) -> list[tuple[trimesh.Trimesh, list[float]]]:
        """What the renderer draws, with a colour each."""
        if self.mesh is not None:
            return [(self.mesh, [0.7, 0.55, 0.42, 1])]
        return [(self.terrain, [0.72, 0.45, 0.3, 1]), (self.objects_mesh, [0.55, 0.4, 0.33, 1])]

    @property
    def solid_mesh(self) -> trimesh.Trimesh:
        """All true geometry, ground included (what the flyer must not touch)."""
        if self.mesh is not None:
            return self.mesh
        return trimesh.util.concatenate([self.terrain, *self.objects])

    def height_at(self, x: np.ndarray | float, y: np.ndarray | float) -> np.ndarray:
        """Terrain height under (x, y), exactly as the rendered mesh has it."""
        xs, ys, Z = self.terrain_xs, self.terrain_ys, self.terrain_z
        x = np.clip(np.asarray(x, dtype=np.float64), xs[0], xs[-1])
        y = np.clip(np.asarray(y, dtype=np.float64), ys[0], ys[-1])
        fx = (x - xs[0]) / (xs[1] - xs[0])
        fy = (y - ys[0]) / (ys[1] - ys[0])
        i = np.clip(np.floor(fx).astype(int), 0, len(xs) - 2)
        j = np.clip(np.floor(fy).astype(int), 0, len(ys) - 2)
        u, v = fx - i, fy - j
        z00, z10 = Z[j, i], Z[j, i + 1]
        z01, z11 = Z[j + 1, i], Z[j + 1, i + 1]
        # Triangles split along (i+1, j) - (i, j+1), as in heightfield_mesh.
        lower = u + v <= 1.0
        z_lower = z00 + u * (z10 - z00) + v * (z01 - z00)
        z_upper = z11 + (1 - u) * (z01 - z11) + (1 - v) * (z10 - z11)
        return np.where(lower, z_lower, z_upper)

    def surface_samples(self, n: int, seed: int = 0) -> np.ndarray:
        """(n', 3) float32 true surface samples inside the box of interest, drawn by area.

        Samples that no camera can ever see are removed: terrain inside a rock, rock below the
        ground, faces buried inside another object. n' is a little below n.
        """
        xmin, ymin, zmin, xmax, ymax, zmax = self.bounds_m
        mesh = self.solid_mesh
        c = mesh.triangles_center
        inside = ((c[:, 0] >= xmin) & (c[:, 0] <= xmax) & (c[:, 1] >= ymin) & (c[:, 1] <= ymax))
        roi = mesh.submesh([np.flatnonzero(inside)], append=True)
        pts, _ = trimesh.sample.sample_surface(roi, n, seed=seed)
        keep = in_region(pts, self.bounds_m)  # the one scored region (see in_region)
        if self.mesh is not None:  # a file's mesh: its inside is not known, keep every sample
            return pts[keep].astype(np.float32)
        keep &= pts[:, 2] >= self.height_at(pts[:, 0], pts[:, 1]) - 0.02
        for obj in self.objects:
            lo, hi = obj.bounds
            near = keep & np.all((pts >= lo - 1e-6) & (pts <= hi + 1e-6), axis=1)
            idx = np.flatnonzero(near)
            if len(idx):
                keep[idx[inside_convex(obj, pts[idx], margin_m=0.01)]] = False
        return pts[keep].astype(np.float32)


def inside_convex(mesh: trimesh.Trimesh, pts: np.ndarray, margin_m: float) -> np.ndarray:
    """Points deeper than ``margin_m`` inside a convex mesh (every object here is convex)."""
    normals = mesh.face_normals
    offsets = np.einsum("ij,ij->i", normals, mesh.triangles[:, 0])
    return np.all(pts @ normals.T - offsets < -margin_m, axis=1)


def heightfield_mesh(xs: np.ndarray, ys: np.ndarray, Z: np.ndarray) -> trimesh.Trimesh:
    """Triangle mesh of a grid heightfield (two triangles a cell)."""
    nx, ny = len(xs), len(ys)
    X, Y = np.meshgrid(xs, ys)
    V = np.c_[X.ravel(), Y.ravel(), Z.ravel()]
    j, i = np.meshgrid(np.arange(ny - 1), np.arange(nx - 1), indexing="ij")
    a = (j * nx + i).ravel()
    b, d = a + 1, a + nx
    e = d + 1
    F = np.concatenate([np.c_[a, b, d], np.c_[b, e, d]])
    return trimesh.Trimesh(V, F, process=False)
