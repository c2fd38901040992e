"""Procedural planetary-analog scenes: terrain, rocks and overhanging structures (trimesh).

A :class:`Scene` holds the true geometry (ground truth lives in ``rover_sim`` only), its box of
interest, its ``d_scene`` (the diagonal of that box, which every tolerance scales with) and its
named starts. Scenes are deterministic: the same name gives the same meshes, bit for bit.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import trimesh

TERRAIN_CELL_M = 0.5


@dataclass
class Scene:
    """True geometry and metadata of one world."""

    name: str
    terrain_xs: np.ndarray
    """(nx,) grid x coordinates of the terrain heightfield."""
    terrain_ys: np.ndarray
    """(ny,) grid y coordinates."""
    terrain_z: np.ndarray
    """(ny, nx) heights; the terrain mesh interpolates them linearly over triangles."""
    objects: list[trimesh.Trimesh]
    """Watertight obstacle meshes (rocks, structures), in map coordinates."""
    bounds_m: tuple[float, float, float, float, float, float]
    """Box of interest (xmin, ymin, zmin, xmax, ymax, zmax): coverage counts what is inside."""
    starts: dict[str, tuple[float, float, float]] = field(default_factory=dict)
    """Named starts: rover base (x, y, yaw)."""

    @property
    def d_scene_m(self) -> float:
        lo, hi = np.array(self.bounds_m[:3]), np.array(self.bounds_m[3:])
        return float(np.linalg.norm(hi - lo))

    @property
    def terrain(self) -> trimesh.Trimesh:
        return heightfield_mesh(self.terrain_xs, self.terrain_ys, self.terrain_z)

    @property
    def objects_mesh(self) -> trimesh.Trimesh:
        return trimesh.util.concatenate(self.objects)

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
        parts = [self.terrain, *self.objects]
        mesh = trimesh.util.concatenate(parts)
        c = mesh.triangles_center
        inside = ((c[:, 0] >= xmin) & (c[:, 0] <= xmax) & (c[:, 1] >= ymin) & (c[:, 1] <= ymax))
        roi = mesh.submesh([np.flatnonzero(inside)], append=True)
        pts, _ = trimesh.sample.sample_surface(roi, n, seed=seed)
        keep = ((pts[:, 0] >= xmin) & (pts[:, 0] <= xmax) & (pts[:, 1] >= ymin)
                & (pts[:, 1] <= ymax))
        keep &= pts[:, 2] >= self.height_at(pts[:, 0], pts[:, 1]) - 0.02
        for obj in self.objects:
            lo, hi = obj.bounds
            near = keep & np.all((pts >= lo - 1e-6) & (pts <= hi + 1e-6), axis=1)
            idx = np.flatnonzero(near)
            if len(idx):
                keep[idx[_inside_convex(obj, pts[idx], margin_m=0.01)]] = False
        return pts[keep].astype(np.float32)


def _inside_convex(mesh: trimesh.Trimesh, pts: np.ndarray, margin_m: float) -> np.ndarray:
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


def _rock(rng: np.random.Generator, radius: float) -> trimesh.Trimesh:
    rock = trimesh.creation.icosphere(subdivisions=2, radius=1.0)
    noise = 1.0 + 0.18 * rng.standard_normal(len(rock.vertices))
    rock.vertices *= noise[:, None]
    rock.vertices *= radius * np.array([1.0, rng.uniform(0.7, 1.0), rng.uniform(0.5, 0.8)])
    rock.apply_transform(trimesh.transformations.rotation_matrix(rng.uniform(0, 2 * np.pi),
                                                                 [0, 0, 1]))
    return trimesh.convex.convex_hull(rock)  # watertight, so "inside" is well defined


def _box(extents, center) -> trimesh.Trimesh:
    return trimesh.creation.box(extents=extents,
                                transform=trimesh.transformations.translation_matrix(center))


def build_arch_field(seed: int = 7) -> Scene:
    """Rolling terrain with ~30 rocks, a natural arch, a hoodoo and a mesa with an overhang.

    The box of interest is 30 m x 30 m; the terrain extends 10 m further so that the horizon
    is not a cliff. Overhangs: the arch's lintel (3 m above the ground, the rover fits under
    it), the hoodoo's cap, and the mesa's overhanging slab.
    """
    rng = np.random.default_rng(seed)
    xs = np.arange(-25.0, 25.0 + 1e-9, TERRAIN_CELL_M)
    ys = xs.copy()
    X, Y = np.meshgrid(xs, ys)
    Z = 0.6 * np.sin(X / 6.0 + 0.4) * np.cos(Y / 8.0 - 0.3)
    for _ in range(6):
        cx, cy = rng.uniform(-20, 20, 2)
        amp, sig = rng.uniform(-0.6, 0.6), rng.uniform(3.0, 6.0)
        Z += amp * np.exp(-((X - cx) ** 2 + (Y - cy) ** 2) / (2 * sig**2))
    scene = Scene("arch_field", xs, ys, Z, [], (0, 0, 0, 0, 0, 0))
    h = scene.height_at

    objects: list[trimesh.Trimesh] = []
    # Natural arch: two pillars and a lintel that rests 3.0 m above the ground between them.
    ax, ay = 6.0, -5.0
    g = float(np.max(h(np.array([ax, ax]), np.array([ay - 2.0, ay + 2.0]))))
    for py in (ay - 2.0, ay + 2.0):
        gp = float(h(ax, py))
        objects.append(_box([1.2, 1.2, g + 3.1 - (gp - 0.5)], [ax, py, (g + 3.1 + gp - 0.5) / 2]))
    objects.append(_box([1.4, 5.6, 0.8], [ax, ay, g + 3.4]))
    # Hoodoo: a narrow pedestal under a wide, flat cap.
    hx, hy = -6.0, -7.0
    g = float(h(hx, hy))
    pedestal = trimesh.creation.cylinder(radius=0.6, height=3.0, sections=16)
    pedestal.apply_translation([hx, hy, g + 1.0])
    cap = trimesh.creation.icosphere(subdivisions=2, radius=1.0)
    cap.vertices *= np.array([2.0, 1.8, 0.6])
    cap.apply_translation([hx, hy, g + 2.8])
    objects += [pedestal, cap]
    # Mesa: a block with a slab that overhangs its south face by 1.5 m.
    mx, my = -7.0, 7.0
    g = float(h(mx, my))
    objects.append(_box([6.0, 3.0, 3.5], [mx, my, g + 1.25]))
    objects.append(_box([6.5, 4.5, 0.6], [mx, my - 0.75, g + 3.2]))

    starts = {"a": (0.0, 0.0, 0.0), "b": (10.0, 8.0, np.pi), "c": (-11.0, 0.0, np.pi / 2),
              "d": (9.0, -12.0, np.pi / 2), "e": (-1.0, 12.0, -np.pi / 2)}
    keep_clear = [(ax, ay, 4.5), (hx, hy, 4.0), (mx, my, 5.5)]
    keep_clear += [(x, y, 2.5) for x, y, _ in starts.values()]
    placed = 0
    while placed < 30:
        x, y = rng.uniform(-16, 16, 2)
        r = float(rng.uniform(0.3, 1.1))
        if any(np.hypot(x - cx, y - cy) < rad + r for cx, cy, rad in keep_clear):
            continue
        rock = _rock(rng, r)
        rock.apply_translation([x, y, float(h(x, y)) + 0.1 * r])
        objects.append(rock)
        keep_clear.append((x, y, r + 0.8))
        placed += 1

    scene.objects = objects
    zmin = float(Z[(np.abs(X) <= 15) & (np.abs(Y) <= 15)].min())
    zmax = max(float(o.bounds[1, 2]) for o in objects)
    scene.bounds_m = (-15.0, -15.0, zmin, 15.0, 15.0, zmax)
    scene.starts = {k: (float(x), float(y), float(t)) for k, (x, y, t) in starts.items()}
    return scene


#: Scene registry: name -> builder. Issue-level extensions add to it.
SCENES: dict[str, Callable[[], Scene]] = {"arch_field": build_arch_field}


def load_scene(name: str) -> Scene:
    """Build a registered scene; an unknown name gives the list of valid ones."""
    if name not in SCENES:
        raise SystemExit(f"error: unknown scene {name!r}; choose one of: {', '.join(SCENES)}")
    return SCENES[name]()


def resolve_scene(cfg_scene) -> None:
    """Fill a SceneConfig's d_scene_m and bounds_m from its scene, where left at zero.

    These are mission parameters the operators know (the area of operations and its size);
    the scene's geometry itself stays in the simulator.
    """
    if cfg_scene.resolved:
        return
    scene = load_scene(cfg_scene.name)
    if cfg_scene.d_scene_m <= 0:
        cfg_scene.d_scene_m = scene.d_scene_m
    if not any(cfg_scene.bounds_m):
        cfg_scene.bounds_m = tuple(float(v) for v in scene.bounds_m)
