"""The scene catalogue: suite scenes by name, mesh files by path, and their fixed starts.

``load_scene`` takes a scene name (``rovergate scenes`` lists them) or the path of any mesh
file trimesh reads. Starts that a scene does not place by hand are chosen here, the same way
for every scene: on a 1 m grid over the box of interest (2 m in from its edge), keep the poses
where the rover (default limits) stands on traversable ground at least 0.3 m from every
obstacle and where the flyer's sphere is 0.2 m clear at its start altitude; keep the largest
connected region of them (so that no start is stranded on a plateau or a roof); then take five
by farthest-point sampling from the pose nearest the centre, each heading for the centre.
"""

from __future__ import annotations

import functools
import importlib.metadata
import logging
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from rover_sim import suite
from rover_sim.scene import Scene
from rovergate.config import FlyerConfig, RoverConfig, SceneConfig
from rovergate.errors import ConfigError, UnknownNameError

log = logging.getLogger("rovergate.scenes")

START_NAMES = ("a", "b", "c", "d", "e")
START_GRID_M = 1.0
START_INSET_M = 2.0
START_ROVER_CLEARANCE_M = 0.3
START_FLYER_CLEARANCE_M = 0.2


@dataclass(frozen=True)
class CatalogEntry:
    build: Callable[[], Scene]
    kind: str
    """'procedural' (the evaluation suite), 'heightmap', 'large' (long missions: not in the
    suite) or 'mesh' (a file shipped with pybullet_data)."""


def _pybullet_mesh(name: str, filename: str, up_axis: str) -> Callable[[], Scene]:
    def build() -> Scene:
        import pybullet_data

        from rover_sim.mesh_scene import load_mesh_scene
        path = Path(pybullet_data.getDataPath()) / filename
        return load_mesh_scene(path, up_axis=up_axis, scale=1.0, region_m=40.0, name=name)
    return build


#: Scene registry: name -> entry. The suite's procedural scenes, then the ready-made meshes.
SCENES: dict[str, CatalogEntry] = {
    "arch_field": CatalogEntry(suite.build_arch_field, "procedural"),
    "crater": CatalogEntry(suite.build_crater, "procedural"),
    "canyon": CatalogEntry(suite.build_canyon, "procedural"),
    "lava_tube": CatalogEntry(suite.build_lava_tube, "procedural"),
    "outpost": CatalogEntry(suite.build_outpost, "procedural"),
    "ruins": CatalogEntry(suite.build_ruins, "procedural"),
    "monastery": CatalogEntry(_pybullet_mesh("monastery", "samurai_monastry.obj", "y"), "mesh"),
    "pb_terrain": CatalogEntry(_pybullet_mesh("pb_terrain", "terrain.obj", "z"), "mesh"),
    "pb_heightmap": CatalogEntry(suite.build_pb_heightmap, "heightmap"),
    "long_traverse": CatalogEntry(suite.build_long_traverse, "large"),
}

#: The evaluation suite: the procedural scenes every study runs on by default.
SUITE = tuple(n for n, e in SCENES.items() if e.kind == "procedural")

MESH_SUFFIXES = (".obj", ".ply", ".stl", ".glb", ".gltf", ".off")

#: The entry-point group through which a package of your own adds scenes (as
#: ``rovergate.planners`` adds planners): in its pyproject.toml,
#: ``[project.entry-points."rovergate.scenes"]`` then ``name = "package.module:build"``, a
#: function of no arguments that returns a :class:`rover_sim.scene.Scene` (for a mesh,
#: :func:`rover_sim.mesh_scene.load_mesh_scene`). Its starts are chosen here when it places
#: none, as for every scene.
SCENE_GROUP = "rovergate.scenes"


def _plugin(ep: importlib.metadata.EntryPoint) -> Callable[[], Scene]:
    def build() -> Scene:
        scene = ep.load()()
        if not isinstance(scene, Scene):
            raise ConfigError(f"scene {ep.name!r} ({ep.value}) built a "
                              f"{type(scene).__name__}, not a rover_sim.scene.Scene; return one")
        return scene
    return build


def catalog() -> dict[str, CatalogEntry]:
    """Every scene by name: :data:`SCENES`, then those installed packages register under
    :data:`SCENE_GROUP` (kind ``plugin``; a name the suite has is not theirs to take: such an
    entry is left out, with a warning)."""
    found = dict(SCENES)
    for ep in importlib.metadata.entry_points(group=SCENE_GROUP):
        if ep.name in SCENES:
            log.warning("scene entry point %r of %s is a suite scene's name; it is ignored",
                        ep.name, ep.value)
        else:
            found[ep.name] = CatalogEntry(_plugin(ep), "plugin")
    return found


def _is_path(name: str) -> bool:
    return "/" in name or Path(name).suffix.lower() in MESH_SUFFIXES


@functools.lru_cache(maxsize=4)
def _load(name: str, up_axis: str, scale: float, region_m: float,
          bounds: tuple[float, ...] | None) -> Scene:
    scenes = catalog()
    if name in scenes:
        if bounds is not None:
            # A resolved config names the scene's own box: that is the scene already built
            # when the config was resolved (building it again cost a study 1.3 s per run).
            own = _load(name, up_axis, scale, region_m, None)
            if tuple(float(v) for v in own.bounds_m) == bounds:
                return own
        scene = scenes[name].build()
        if not scene.starts:
            scene.starts = choose_starts(scene)
        if bounds is not None:
            scene.bounds_m = bounds
        return scene
    if _is_path(name):
        from rover_sim.mesh_scene import load_mesh_scene
        scene = load_mesh_scene(Path(name), up_axis=up_axis, scale=scale, region_m=region_m,
                                bounds_m=bounds)
        scene.starts = choose_starts(scene)
        return scene
    raise UnknownNameError(f"unknown scene {name!r}; choose one of: {', '.join(scenes)}, or "
                           "pass the path of a mesh file (OBJ, PLY, STL, GLB)")


def load_scene(spec: str | SceneConfig) -> Scene:
    """A scene by name or mesh path (a string), or as a mission's SceneConfig describes it.

    Within one process the same scene is built once (the simulator and the run share it).
    """
    if isinstance(spec, str):
        return _load(spec, "z", 1.0, 40.0, None)
    bounds = tuple(float(v) for v in spec.bounds_m) if any(spec.bounds_m) else None
    return _load(spec.name, spec.up_axis, float(spec.scale), float(spec.region_m), bounds)


def resolve_scene(cfg_scene: SceneConfig) -> None:
    """Fill a SceneConfig's d_scene_m and bounds_m from its scene, where left at zero.

    These are mission parameters the operators know (the area of operations and its size);
    the scene's geometry itself stays in the simulator.
    """
    if cfg_scene.resolved:
        return
    scene = load_scene(cfg_scene)  # its box of interest is the config's, where one is given
    if not any(cfg_scene.bounds_m):
        cfg_scene.bounds_m = tuple(float(v) for v in scene.bounds_m)
    if cfg_scene.d_scene_m <= 0:
        cfg_scene.d_scene_m = scene.d_scene_m


def start_candidates(scene: Scene, rover: RoverConfig | None = None,
                     flyer: FlyerConfig | None = None
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The (nx,) and (ny,) grid coordinates, and the (ny, nx) bool grid of the poses fit for
    both platforms."""
    from rover_sim.flyer import FlyerBody
    from rover_sim.rover import RoverBody
    rover, flyer = rover or RoverConfig(), flyer or FlyerConfig()
    xmin, ymin, _, xmax, ymax, _ = scene.bounds_m
    xs = np.arange(xmin + START_INSET_M, xmax - START_INSET_M + 1e-9, START_GRID_M)
    ys = np.arange(ymin + START_INSET_M, ymax - START_INSET_M + 1e-9, START_GRID_M)
    cx, cy = (xmin + xmax) / 2, (ymin + ymax) / 2
    body = RoverBody(scene, rover)
    fly = FlyerBody(scene, flyer, rover.check_spacing_m)
    ok = np.zeros((len(ys), len(xs)), dtype=bool)
    for j, y in enumerate(ys):
        for i, x in enumerate(xs):
            yaw = float(np.arctan2(cy - y, cx - x))
            if not body.traversable(x, y, yaw):
                continue
            if body.clearance(body.base_pose(x, y, yaw)) < START_ROVER_CLEARANCE_M:
                continue
            z = float(scene.height_at(x, y)) + flyer.altitude_m
            ok[j, i] = fly.clearance((x, y, z)) >= START_FLYER_CLEARANCE_M
    return xs, ys, ok


def choose_starts(scene: Scene, n: int = 5) -> dict[str, tuple[float, float, float]]:
    """Five named starts (see the module docstring); deterministic for a scene."""
    from scipy.ndimage import label  # (scenes without starts only: 0.25 s of start-up)
    xs, ys, ok = start_candidates(scene)
    labels, count = label(ok, structure=np.ones((3, 3)))
    if count == 0:
        raise ConfigError(f"scene {scene.name!r} has no place where the rover fits on "
                          "traversable ground inside its box of interest; pass a larger "
                          "--scene.bounds-m or check the mesh's --scene.up-axis and "
                          "--scene.scale")
    sizes = np.bincount(labels.ravel())[1:]
    rows, cols = np.nonzero(labels == 1 + int(np.argmax(sizes)))
    pts = np.c_[xs[cols], ys[rows]]
    xmin, ymin, _, xmax, ymax, _ = scene.bounds_m
    centre = np.array([(xmin + xmax) / 2, (ymin + ymax) / 2])
    chosen = [int(np.argmin(np.linalg.norm(pts - centre, axis=1)))]
    d = np.linalg.norm(pts - pts[chosen[0]], axis=1)
    while len(chosen) < min(n, len(pts)):
        k = int(np.argmax(d))
        chosen.append(k)
        d = np.minimum(d, np.linalg.norm(pts - pts[k], axis=1))
    out = {}
    for name, k in zip(START_NAMES, chosen, strict=False):
        x, y = (float(v) for v in pts[k])
        yaw = float(np.arctan2(centre[1] - y, centre[0] - x)) if k != chosen[0] else 0.0
        out[name] = (x, y, yaw)
    return out
