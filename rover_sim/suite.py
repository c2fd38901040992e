"""The scene suite: procedural planetary-analog worlds, each deterministic from its seed.

Every scene is a terrain heightfield (0.5 m cells, reaching 10 m beyond the box of interest so
that the horizon is not a cliff) plus convex obstacle meshes; larger structures (a dome, a lava
tube) are built from convex pieces, so that "inside an object" stays well defined for the
ground-truth samples. Each scene stresses the planner differently:

========== ==================================================================================
arch_field rolling ground, 30 rocks, a natural arch, a hoodoo and an overhanging mesa
crater     craters with raised rims and steep bowls (untraversable), boulders and ejecta
canyon     a meandering canyon, cliffs the rover cannot climb, overhanging ledges, boulders
lava_tube  a ramp down into a lava tube: a ceiling overhead, a skylight, rubble
outpost    inspection of structures: habitats, a lander the rover fits under, an antenna
           mast, solar arrays on posts, crates
ruins      columns (standing and fallen), arches, broken walls and a domed hall with a door
========== ==================================================================================
"""

from __future__ import annotations

import numpy as np
import trimesh

from rover_sim.scene import Scene

TERRAIN_CELL_M = 0.5
HALF_ROI_M = 15.0
HALF_TERRAIN_M = 25.0


def _grid() -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    xs = np.arange(-HALF_TERRAIN_M, HALF_TERRAIN_M + 1e-9, TERRAIN_CELL_M)
    X, Y = np.meshgrid(xs, xs)
    return xs, xs.copy(), X, Y


def _rolling(rng: np.random.Generator, X: np.ndarray, Y: np.ndarray, amp: float = 0.4,
             bumps: int = 6) -> np.ndarray:
    Z = amp * np.sin(X / 6.0 + rng.uniform(0, 6)) * np.cos(Y / 8.0 + rng.uniform(0, 6))
    for _ in range(bumps):
        cx, cy = rng.uniform(-20, 20, 2)
        a, sig = rng.uniform(-amp, amp), rng.uniform(3.0, 6.0)
        Z += a * np.exp(-((X - cx) ** 2 + (Y - cy) ** 2) / (2 * sig**2))
    return Z


def _rock(rng: np.random.Generator, radius: float) -> trimesh.Trimesh:
    rock = trimesh.creation.icosphere(subdivisions=2, radius=1.0)
    noise = 1.0 + 0.18 * rng.standard_normal(len(rock.vertices))
    rock.vertices *= noise[:, None]
    rock.vertices *= radius * np.array([1.0, rng.uniform(0.7, 1.0), rng.uniform(0.5, 0.8)])
    rock.apply_transform(trimesh.transformations.rotation_matrix(rng.uniform(0, 2 * np.pi),
                                                                 [0, 0, 1]))
    return trimesh.convex.convex_hull(rock)  # watertight, so "inside" is well defined


def _box(extents, center, yaw: float = 0.0, pitch: float = 0.0) -> trimesh.Trimesh:
    T = trimesh.transformations.euler_matrix(0.0, pitch, yaw, "sxyz")
    T[:3, 3] = center
    return trimesh.creation.box(extents=extents, transform=T)


def _cylinder(radius: float, height: float, center, axis=(0, 0, 1),
              sections: int = 20) -> trimesh.Trimesh:
    c = trimesh.creation.cylinder(radius=radius, height=height, sections=sections)
    axis = np.asarray(axis, dtype=float)
    T = trimesh.geometry.align_vectors([0, 0, 1], axis / np.linalg.norm(axis))
    c.apply_transform(T)
    c.apply_translation(center)
    return c


def _hull(points) -> trimesh.Trimesh:
    return trimesh.convex.convex_hull(np.asarray(points, dtype=float))


def _dome_pieces(center, r_in: float, r_out: float, n_az: int, n_el: int,
                 skip=lambda ia, ie: False) -> list[trimesh.Trimesh]:
    """A hemispherical shell as convex patches (each the hull of its corners)."""
    cx, cy, cz = center
    pieces = []
    for ia in range(n_az):
        for ie in range(n_el):
            if skip(ia, ie):
                continue
            az = np.linspace(2 * np.pi * ia / n_az, 2 * np.pi * (ia + 1) / n_az, 3)
            el = np.linspace(0.5 * np.pi * ie / n_el, 0.5 * np.pi * (ie + 1) / n_el, 3)
            A, E = np.meshgrid(az, el)
            pts = [np.c_[cx + r * np.cos(E.ravel()) * np.cos(A.ravel()),
                         cy + r * np.cos(E.ravel()) * np.sin(A.ravel()),
                         cz + r * np.sin(E.ravel())] for r in (r_in, r_out)]
            pieces.append(_hull(np.vstack(pts)))
    return pieces


def _tube_pieces(x0: float, x1: float, y0: float, z0: float, r_in: float, r_out: float,
                 n_th: int, n_x: int, skip=lambda ith, ix: False) -> list[trimesh.Trimesh]:
    """A half-cylinder shell along x (axis at height z0) as convex patches."""
    pieces = []
    xs = np.linspace(x0, x1, n_x + 1)
    for ix in range(n_x):
        for ith in range(n_th):
            if skip(ith, ix):
                continue
            th = np.linspace(np.pi * ith / n_th, np.pi * (ith + 1) / n_th, 3)
            pts = [np.c_[np.full(3, x), y0 + r * np.cos(th), z0 + r * np.sin(th)]
                   for x in xs[ix:ix + 2] for r in (r_in, r_out)]
            pieces.append(_hull(np.vstack(pts)))
    return pieces


def _scatter_rocks(rng: np.random.Generator, scene: Scene, objects: list, n: int,
                   r_range: tuple[float, float], keep_clear: list[tuple[float, float, float]],
                   area: tuple[float, float, float, float] = (-14, -14, 14, 14),
                   ok=lambda x, y: True, max_tries: int = 20_000) -> None:
    """Place ``n`` rocks at random, away from ``keep_clear`` discs and from each other."""
    placed = tries = 0
    while placed < n and tries < max_tries:
        tries += 1
        x, y = rng.uniform(area[0], area[2]), rng.uniform(area[1], area[3])
        r = float(rng.uniform(*r_range))
        if not ok(x, y) or any(np.hypot(x - cx, y - cy) < rad + r for cx, cy, rad in keep_clear):
            continue
        rock = _rock(rng, r)
        rock.apply_translation([x, y, float(scene.height_at(x, y)) + 0.1 * r])
        objects.append(rock)
        keep_clear.append((x, y, r + 0.8))
        placed += 1


def _finish(scene: Scene, objects: list[trimesh.Trimesh], X: np.ndarray, Y: np.ndarray,
            starts: dict | None = None, half_x: float = HALF_ROI_M,
            half_y: float = HALF_ROI_M) -> Scene:
    scene.objects = objects
    roi = (np.abs(X) <= half_x) & (np.abs(Y) <= half_y)
    zmin = float(scene.terrain_z[roi].min())
    tops = [float(scene.terrain_z[roi].max())]
    for o in objects:
        v = o.vertices
        inside = (np.abs(v[:, 0]) <= half_x) & (np.abs(v[:, 1]) <= half_y)
        if inside.any():
            tops.append(float(v[inside, 2].max()))
    zmax = max(tops)
    scene.bounds_m = (-half_x, -half_y, zmin, half_x, half_y, zmax)
    if starts:
        scene.starts = {k: (float(x), float(y), float(t)) for k, (x, y, t) in starts.items()}
    return scene


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
    scene = Scene("arch_field", xs, ys, Z, [], (0, 0, 0, 0, 0, 0),
                  description="rolling ground, rocks, a natural arch, a hoodoo, a mesa")
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



def build_crater(seed: int = 11) -> Scene:
    """Craters with raised rims and bowls too steep to enter, boulders and ejecta blocks."""
    rng = np.random.default_rng(seed)
    xs, ys, X, Y = _grid()
    Z = _rolling(rng, X, Y, amp=0.3)
    craters: list[tuple[float, float, float]] = []
    while len(craters) < 6:
        cx, cy = rng.uniform(-13, 13, 2)
        R = float(rng.uniform(2.5, 6.0))
        if any(np.hypot(cx - x, cy - y) < 1.3 * (R + r) for x, y, r in craters):
            continue
        craters.append((float(cx), float(cy), R))
        r = np.hypot(X - cx, Y - cy)
        # The bowl's wall is ~31 degrees at the rim: the rover cannot drive in.
        Z += np.where(r < R, -0.3 * R * (1 - (r / R) ** 2), 0.0)
        Z += 0.08 * R * np.exp(-(((r - R) / (0.35 * R)) ** 2))
    scene = Scene("crater", xs, ys, Z, [], (0, 0, 0, 0, 0, 0),
                  description="craters with steep bowls and raised rims, boulders, ejecta")
    objects: list[trimesh.Trimesh] = []
    keep = [(x, y, R * 0.9) for x, y, R in craters]
    _scatter_rocks(rng, scene, objects, 25, (0.4, 1.3), keep)
    for cx, cy, R in craters:  # ejecta just outside the rims
        def near_rim(x, y, cx=cx, cy=cy, R=R):
            return R * 1.1 < np.hypot(x - cx, y - cy) < R * 1.7
        _scatter_rocks(rng, scene, objects, 3, (0.2, 0.5), keep,
                       area=(cx - 1.7 * R, cy - 1.7 * R, cx + 1.7 * R, cy + 1.7 * R),
                       ok=near_rim, max_tries=2000)
    return _finish(scene, objects, X, Y)


def build_canyon(seed: int = 12) -> Scene:
    """A meandering canyon: cliffs the rover cannot climb, ledges overhanging the floor."""
    rng = np.random.default_rng(seed)
    xs, ys, X, Y = _grid()
    phase = rng.uniform(0, 2 * np.pi)

    def centre(y):
        return 2.5 * np.sin(y / 6.0 + phase)

    def half_width(y):
        return 4.0 + 1.0 * np.cos(y / 5.0 + phase)

    d = np.abs(X - centre(Y)) - half_width(Y)  # > 0 outside the floor
    wall_h = 6.0 + _rolling(rng, X, Y, amp=0.6, bumps=4)
    Z = 0.15 * np.sin(X * 1.3) * np.cos(Y * 0.9) + wall_h * np.clip(d / 1.5, 0, 1) ** 2
    scene = Scene("canyon", xs, ys, Z, [], (0, 0, 0, 0, 0, 0),
                  description="a meandering canyon: cliffs, overhanging ledges, boulders")
    objects: list[trimesh.Trimesh] = []
    for k, y in enumerate(np.linspace(-12, 12, 6)):
        side = 1 if k % 2 else -1
        wall_x = float(centre(y) + side * half_width(y))
        z = float(rng.uniform(2.5, 4.0))
        out = float(rng.uniform(1.8, 2.6))
        # From 1.5 m inside the cliff to ``out`` metres over the floor.
        objects.append(_box([out + 1.5, float(rng.uniform(3, 5)), 0.6],
                            [wall_x + side * (1.5 - out) / 2, y, z]))
    _scatter_rocks(rng, scene, objects, 18, (0.3, 1.0), [],
                   ok=lambda x, y: abs(x - centre(y)) < half_width(y) - 1.0)
    return _finish(scene, objects, X, Y, half_x=9.0)


def build_lava_tube(seed: int = 13) -> Scene:
    """A ramp down into a lava tube: the ceiling 4 m over the floor, a skylight, rubble."""
    rng = np.random.default_rng(seed)
    xs, ys, X, Y = _grid()
    Z = _rolling(rng, X, Y, amp=0.25)
    floor_z, r_in, r_out = -2.0, 4.0, 5.0
    ay = np.abs(Y)
    in_tube = X >= 0.0
    ramp = (X < 0.0) & (X > -7.0)
    ramp_z = floor_z * (X + 7.0) / 7.0  # 16 degrees: drivable
    under_wall = floor_z + np.clip((ay - r_in) / 1.5, 0, 1) * (-floor_z)
    Z = np.where(in_tube & (ay <= r_in + 1.5), under_wall + 0.05 * np.sin(X), Z)
    Z = np.where(ramp & (ay <= r_in), np.minimum(Z, ramp_z), Z)
    scene = Scene("lava_tube", xs, ys, Z, [], (0, 0, 0, 0, 0, 0),
                  description="a ramp into a lava tube: ceiling overhead, skylight, rubble")
    # The tube's roof, in 2 m slices; the skylight is two missing patches at x 8..10.
    objects = _tube_pieces(0.0, 18.0, 0.0, floor_z, r_in, r_out, n_th=8, n_x=9,
                           skip=lambda ith, ix: ix == 4 and ith in (3, 4))
    _scatter_rocks(rng, scene, objects, 12, (0.25, 0.6), [], area=(-6, -3, 14, 3))
    _scatter_rocks(rng, scene, objects, 15, (0.4, 1.1), [],
                   ok=lambda x, y: abs(y) > r_out + 1.5 or x < -8.5)
    return _finish(scene, objects, X, Y)


def build_outpost(seed: int = 14) -> Scene:
    """Structures to inspect: habitats, a lander to drive under, a mast, solar arrays."""
    rng = np.random.default_rng(seed)
    xs, ys, X, Y = _grid()
    Z = _rolling(rng, X, Y, amp=0.15)
    scene = Scene("outpost", xs, ys, Z, [], (0, 0, 0, 0, 0, 0),
                  description="habitats, a lander to pass under, an antenna mast, solar arrays")
    h = scene.height_at
    objects: list[trimesh.Trimesh] = []
    # Two habitat modules and the node between them.
    for cx in (-6.0, 2.0):
        g = float(h(cx, 6.0))
        objects.append(_cylinder(1.6, 6.0, [cx, 6.0, g + 1.75], axis=(1, 0, 0)))
    g = float(h(-2.0, 6.0))
    objects.append(_box([2.2, 2.2, 2.8], [-2.0, 6.0, g + 1.3]))
    # Lander: body 1.5 m over the ground on four legs; the engine bell ends 1.0 m up, so the
    # rover (0.9 m tall) fits under it with 10 cm to spare.
    lx, ly = 8.0, -5.0
    g = float(h(lx, ly))
    objects.append(_cylinder(1.4, 1.8, [lx, ly, g + 2.4]))
    bell = trimesh.creation.cone(radius=0.6, height=0.5, sections=16)
    bell.apply_transform(trimesh.transformations.rotation_matrix(np.pi, [1, 0, 0]))
    bell.apply_translation([lx, ly, g + 1.5])
    objects.append(bell)
    for a in np.arange(4) * np.pi / 2 + np.pi / 4:
        fx, fy = lx + 2.0 * np.cos(a), ly + 2.0 * np.sin(a)
        gf = float(h(fx, fy))
        top = np.array([lx + 1.2 * np.cos(a), ly + 1.2 * np.sin(a), g + 2.0])
        foot = np.array([fx, fy, gf + 0.05])
        objects.append(_cylinder(0.1, float(np.linalg.norm(top - foot)), (top + foot) / 2,
                                 axis=top - foot, sections=8))
        objects.append(_cylinder(0.35, 0.1, [fx, fy, gf + 0.05], sections=12))
    # Antenna mast and its dish.
    mx, my = -9.0, -8.0
    g = float(h(mx, my))
    objects.append(_cylinder(0.15, 7.0, [mx, my, g + 3.4], sections=10))
    dish = trimesh.creation.icosphere(subdivisions=2, radius=1.0)
    dish.vertices *= [1.3, 1.3, 0.3]
    dish.apply_transform(trimesh.transformations.rotation_matrix(np.radians(50), [0, 1, 0]))
    dish.apply_translation([mx + 0.4, my, g + 7.0])
    objects.append(dish)
    # Solar arrays: panels tilted 25 degrees on posts; the lowest edge is 1.25 m up.
    for px in (-5.0, -2.0, 1.0, 4.0):
        py = -11.0
        g = float(h(px, py))
        objects.append(_box([2.6, 1.6, 0.06], [px, py, g + 1.6], pitch=0.0,
                            yaw=0.0).apply_transform(_about([px, py, g + 1.6],
                                                            np.radians(25), [1, 0, 0])))
        objects.append(_cylinder(0.08, 1.55, [px, py, g + 0.75], sections=8))
    # Crates beside the habitats.
    for k in range(8):
        cx, cy = -9.0 + 2.2 * k, float(rng.uniform(1.8, 2.8))
        e = float(rng.uniform(0.7, 1.1))
        objects.append(_box([e, e, e], [cx, cy, float(h(cx, cy)) + e / 2 - 0.05],
                            yaw=float(rng.uniform(0, np.pi / 2))))
    keep = [(-2.0, 6.0, 6.0), (lx, ly, 3.5), (mx, my, 2.5), (-0.5, -11.0, 5.0), (-1.5, 2.3, 9.0)]
    _scatter_rocks(rng, scene, objects, 10, (0.3, 0.8), keep)
    return _finish(scene, objects, X, Y)


def _about(point, angle: float, axis) -> np.ndarray:
    return trimesh.transformations.rotation_matrix(angle, axis, point)


def build_ruins(seed: int = 15) -> Scene:
    """Columns (standing, broken, fallen), arches, broken walls and a domed hall."""
    rng = np.random.default_rng(seed)
    xs, ys, X, Y = _grid()
    Z = _rolling(rng, X, Y, amp=0.3)
    scene = Scene("ruins", xs, ys, Z, [], (0, 0, 0, 0, 0, 0),
                  description="columns standing and fallen, arches, broken walls, a domed hall")
    h = scene.height_at
    objects: list[trimesh.Trimesh] = []
    # Colonnade: two rows of six columns; some broken, beams on the intact pairs.
    heights = {}
    for row in (-3.0, 3.0):
        for k in range(6):
            cx = -12.0 + 2.0 * k
            g = float(h(cx, row))
            ht = 4.0 if rng.uniform() > 0.3 else float(rng.uniform(1.2, 2.5))
            heights[(row, k)] = (ht, g)
            objects.append(_cylinder(0.4, ht + 0.3, [cx, row, g + ht / 2 - 0.15], sections=14))
        for k in range(5):
            (h0, g0), (h1, g1) = heights[(row, k)], heights[(row, k + 1)]
            if h0 == 4.0 and h1 == 4.0:
                objects.append(_box([2.8, 0.9, 0.5], [-11.0 + 2.0 * k, row,
                                                      max(g0, g1) + 4.25]))
    for fx, fy, a in ((-9.0, -8.0, 0.4), (-4.0, 9.0, -1.1)):  # fallen columns
        objects.append(_cylinder(0.4, 3.5, [fx, fy, float(h(fx, fy)) + 0.3],
                                 axis=(np.cos(a), np.sin(a), 0), sections=14))
    # Two free-standing arches (a half-ring of convex voussoirs on two piers).
    for ax in (5.0, 10.0):
        ay = -8.0
        g = float(max(h(ax - 1.9, ay), h(ax + 1.9, ay)))
        for px in (ax - 1.9, ax + 1.9):
            gp = float(h(px, ay))
            objects.append(_box([0.8, 0.8, g + 2.5 - gp + 0.3], [px, ay, (g + 2.5 + gp - 0.3) / 2]))
        ring = _tube_pieces(-0.4, 0.4, 0.0, 0.0, 1.5, 2.3, n_th=7, n_x=1)
        T = _about([0, 0, 0], np.pi / 2, [0, 0, 1])
        T[:3, 3] = [ax, ay, g + 2.5]
        objects += [p.apply_transform(T) for p in ring]
    # Domed hall: a drum of wall segments (one left out: the door) under a shell with an
    # oculus at the top.
    dx, dy, R = 6.0, 6.0, 4.0
    g = float(h(dx, dy))
    n = 12
    for k in range(n):
        if k == 6:  # the door faces -x
            continue
        a = np.linspace(2 * np.pi * k / n, 2 * np.pi * (k + 1) / n, 3)
        ring = [np.c_[dx + r * np.cos(a), dy + r * np.sin(a)] for r in (R, R + 0.5)]
        base = np.vstack(ring)
        objects.append(_hull(np.vstack([np.c_[base, np.full(len(base), g - 0.5)],
                                        np.c_[base, np.full(len(base), g + 2.5)]])))
    objects += _dome_pieces([dx, dy, g + 2.5], R, R + 0.5, n_az=n, n_el=4,
                            skip=lambda ia, ie: ie == 3)
    # Broken walls.
    for wx, wy, length, yaw in ((-6.0, -12.0, 4.5, 0.2), (12.0, 0.0, 3.5, 1.4),
                                (-13.0, 10.0, 4.0, 0.9), (1.0, 12.0, 3.0, -0.3)):
        ht = float(rng.uniform(1.0, 2.2))
        objects.append(_box([length, 0.5, ht + 0.3], [wx, wy, float(h(wx, wy)) + ht / 2 - 0.15],
                            yaw=yaw))
    keep = [(-7.0, 0.0, 6.5), (7.5, -8.0, 4.0), (dx, dy, R + 1.5)]
    keep += [(-9.0, -8.0, 2.5), (-4.0, 9.0, 2.5)]
    _scatter_rocks(rng, scene, objects, 15, (0.2, 0.6), keep)
    return _finish(scene, objects, X, Y)


def build_pb_heightmap(metres_per_pixel: float = 0.1, relief_m: float = 6.0) -> Scene:
    """The `pybullet_data` heightmap `heightmaps/wm_height_out.png` (512 x 512, eroded
    terrain from World Machine) as ground: 0.1 m a pixel (51.2 m across), 6 m of relief,
    averaged onto the suite's 0.5 m cells; the box of interest is its central 30 m."""
    import matplotlib.image
    import pybullet_data
    img = matplotlib.image.imread(f"{pybullet_data.getDataPath()}/heightmaps/wm_height_out.png")
    k = int(round(TERRAIN_CELL_M / metres_per_pixel))
    n = img.shape[0] // k
    Z = img[: n * k, : n * k].reshape(n, k, n, k).mean(axis=(1, 3)).astype(np.float64)
    Z = (Z - Z.mean()) * relief_m / max(float(np.ptp(Z)), 1e-9)
    xs = (np.arange(n) - (n - 1) / 2) * TERRAIN_CELL_M
    X, Y = np.meshgrid(xs, xs)
    scene = Scene("pb_heightmap", xs, xs.copy(), Z, [], (0, 0, 0, 0, 0, 0),
                  description="pybullet_data heightmap wm_height_out.png: eroded valleys")
    return _finish(scene, [], X, Y)


#: The long-traverse scene's box of interest (half-edge) and terrain cell: large enough that a
#: rover keeps finding new ground for thousands of steps (issue 30's soak).
TRAVERSE_HALF_ROI_M = 120.0
TRAVERSE_CELL_M = 1.0


def build_long_traverse(seed: int = 21) -> Scene:
    """A 240 m x 240 m plain for long missions: gentle rolling ground (hills tens of metres
    across) and 600 rocks, on 1 m terrain cells reaching 10 m beyond the box of interest.

    Not in the evaluation suite: at this size the suite's fractional tolerances (tau, epsilon
    and delta are fractions of d_scene, 340 m here) are metres wide, so a mission on it sets
    them in absolute terms (``benchmarks/bench_long.py`` does).
    """
    rng = np.random.default_rng(seed)
    half = TRAVERSE_HALF_ROI_M + 10.0
    xs = np.arange(-half, half + 1e-9, TRAVERSE_CELL_M)
    X, Y = np.meshgrid(xs, xs)
    Z = 1.5 * np.sin(X / 18.0 + 0.4) * np.cos(Y / 24.0 - 0.3)
    for _ in range(40):
        cx, cy = rng.uniform(-half, half, 2)
        amp, sig = rng.uniform(-1.0, 1.0), rng.uniform(6.0, 14.0)
        Z += amp * np.exp(-((X - cx) ** 2 + (Y - cy) ** 2) / (2 * sig**2))
    scene = Scene("long_traverse", xs, xs.copy(), Z, [], (0, 0, 0, 0, 0, 0),
                  description="a 240 m plain: rolling ground and 600 rocks (long missions)")
    starts = {"a": (0.0, 0.0, 0.0), "b": (60.0, 40.0, np.pi), "c": (-70.0, 10.0, np.pi / 2),
              "d": (40.0, -80.0, np.pi / 2), "e": (-20.0, 90.0, -np.pi / 2)}
    keep = [(x, y, 3.0) for x, y, _ in starts.values()]
    objects: list[trimesh.Trimesh] = []
    edge = TRAVERSE_HALF_ROI_M - 2.0
    _scatter_rocks(rng, scene, objects, 600, (0.3, 1.2), keep, area=(-edge, -edge, edge, edge))
    return _finish(scene, objects, X, Y, starts, TRAVERSE_HALF_ROI_M, TRAVERSE_HALF_ROI_M)
