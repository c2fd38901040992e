"""`rovergate eval-model`: how well the learned occupancy completes held-out scenes.

On scenes never used in training (the evaluation suite, whose seeds training never uses, and
the mesh scenes), seeded walks of both platforms are mapped exactly as in a mission. At a few
steps of each walk three maps are scored against the true surface:

- ``obs``: the observed surface S_t alone;
- ``geometric``: S_t plus a 2.5-D height-map completion (each unreached column of the grid
  takes the lowest observed surface of its nearest observed column);
- ``learned``: S_t plus the thresholded prediction, as the mapper publishes it.

Precision is the share of a map's points within delta of the true surface; recall the share of
true surface samples within delta of a map point; F their harmonic mean. Both are counted
only where the model's window has been (the same region for every map, inside the box of
interest), and split by whether depth has reached the place (its grid voxel is free or
occupied: *observed*) or not (*unobserved*). Counts are pooled over all snapshots.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from mapper.grid import FREE, OCCUPIED, OccupancyGrid
from mapper.mapper import Mapper
from mission.learning.walks import walk
from rovergate.config import MapperConfig
from rovergate.types import CameraIntrinsics, Pose, SensorFrame, xyz

METHODS = ("obs", "geometric", "learned")
REGIONS = ("observed", "unobserved")


@dataclass
class EvalModelConfig:
    """Precision / recall / F-score of the learned occupancy on held-out scenes."""

    scenes: tuple[str, ...] = ("arch_field", "crater", "canyon", "lava_tube", "outpost",
                               "ruins", "monastery", "pb_terrain", "pb_heightmap")
    """Held-out scenes: suite names or mesh paths (none of them is a training world)."""
    platforms: tuple[str, ...] = ("rover", "flyer")
    """Platforms whose walks are evaluated."""
    walks: int = 2
    """Seeded walks per scene and platform."""
    steps: int = 20
    """Poses per walk."""
    score_at: tuple[int, ...] = (5, 10, 20)
    """Steps of each walk at which the maps are scored."""
    delta_fracs: tuple[float, ...] = (0.03, 0.01)
    """Tolerances, as fractions of d_scene."""
    checkpoint: str = ""
    """Weights to evaluate. Empty: the shipped checkpoint."""
    seed: int = 0
    """Seed of the walks."""
    threads: int = 2
    """Torch threads."""
    out: Path = field(default_factory=lambda: Path("runs/eval-model"))
    """Where results.json and table.md go."""


def heightmap_completion(grid: OccupancyGrid, region: np.ndarray) -> np.ndarray:
    """(M, 3) float32 points of the geometric baseline inside ``region`` (a grid bool mask).

    Every grid column with no return takes, from its nearest column with one, the height of
    that column's lowest return (the ground, where the ground was seen); the voxel at that
    height gets a point unless a ray has shown it free.
    """
    occ = (grid.state & OCCUPIED) != 0
    has = occ.any(axis=2)
    fill = ~has & region.any(axis=2)
    if not has.any() or not fill.any():
        return np.zeros((0, 3), dtype=np.float32)
    k_low = np.argmax(occ, axis=2)
    seen = np.argwhere(has)
    todo = np.argwhere(fill)
    _, nearest = cKDTree(seen).query(todo)
    k = k_low[seen[nearest, 0], seen[nearest, 1]]
    ijk = np.c_[todo, k]
    keep = (grid.state[ijk[:, 0], ijk[:, 1], ijk[:, 2]] != FREE) & region[tuple(ijk.T)]
    return grid.spec.centres(ijk[keep])


@dataclass
class Counts:
    """Pooled counts of one (method, delta, region)."""

    map_points: int = 0
    map_hits: int = 0
    truth_points: int = 0
    truth_hits: int = 0

    def add(self, other: Counts) -> None:
        self.map_points += other.map_points
        self.map_hits += other.map_hits
        self.truth_points += other.truth_points
        self.truth_hits += other.truth_hits

    def scores(self) -> dict[str, float | None]:
        p = self.map_hits / self.map_points if self.map_points else None
        r = self.truth_hits / self.truth_points if self.truth_points else None
        f = (2 * p * r / (p + r) if p is not None and r is not None and p + r > 0
             else (0.0 if p is not None and r is not None else None))
        return {"precision": p, "recall": r, "f": f, "map_points": self.map_points,
                "truth_points": self.truth_points}


def score_maps(maps: dict[str, np.ndarray], truth: np.ndarray, truth_tree: cKDTree,
               grid: OccupancyGrid, region: np.ndarray, bounds_m: tuple[float, ...],
               deltas_m: list[float]) -> dict[tuple[str, int, str], Counts]:
    """Counts of every map at every tolerance, in the observed and unobserved region."""
    spec = grid.spec

    def in_region(p: np.ndarray) -> np.ndarray:
        ijk, inside = spec.index(p)
        ok = inside.copy()
        ok[inside] = region[tuple(ijk[inside].T)]
        lo, hi = np.array(bounds_m[:3]), np.array(bounds_m[3:])
        return ok & np.all((p[:, :2] >= lo[:2]) & (p[:, :2] <= hi[:2]), axis=1)

    t_in = in_region(truth)
    t_known = grid.known(truth)
    out: dict[tuple[str, int, str], Counts] = {}
    for name, pts in maps.items():
        p_in = in_region(pts) if len(pts) else np.zeros(0, dtype=bool)
        p_known = grid.known(pts) if len(pts) else np.zeros(0, dtype=bool)
        d_map = (truth_tree.query(pts[p_in], distance_upper_bound=max(deltas_m))[0]
                 if p_in.any() else np.zeros(0))
        d_truth = (cKDTree(pts).query(truth[t_in], distance_upper_bound=max(deltas_m))[0]
                   if len(pts) else np.full(int(t_in.sum()), np.inf))
        for di, delta in enumerate(deltas_m):
            for region_name, want in zip(REGIONS, (True, False), strict=True):
                pm = p_known[p_in] == want
                tm = t_known[t_in] == want
                out[(name, di, region_name)] = Counts(
                    int(pm.sum()), int((d_map[pm] <= delta).sum()),
                    int(tm.sum()), int((d_truth[tm] <= delta).sum()))
    return out


def evaluate_scene(cfg: EvalModelConfig, scene_name: str, scene_index: int,
                   checkpoint) -> dict[tuple[str, int, str], Counts]:
    """Pooled counts over every walk and scoring step of one scene."""
    from rover_sim.catalog import load_scene
    scene = load_scene(scene_name)
    truth = scene.surface_samples(100_000, seed=0)
    tree = cKDTree(truth)
    deltas = [f * scene.d_scene_m for f in cfg.delta_fracs]
    total: dict[tuple[str, int, str], Counts] = {}
    for p, platform in enumerate(cfg.platforms):
        for w in range(cfg.walks):
            mapper = Mapper(MapperConfig(), scene.bounds_m, checkpoint)
            seed = cfg.seed * 1_000_003 + 900_000 + 1000 * scene_index + 10 * p + w
            for frame in walk(scene, platform, cfg.steps, seed):
                k: CameraIntrinsics = frame.intrinsics
                pose = Pose.from_matrix(frame.T_map_camera)
                out = mapper.step(SensorFrame(frame.step, frame.depth_m, k, pose, pose))
                if frame.step not in cfg.score_at:
                    continue
                region = mapper.predictor.covered
                s_xyz = xyz(out.surface)
                maps = {"obs": s_xyz,
                        "geometric": np.concatenate(
                            [s_xyz, heightmap_completion(mapper.grid, region)]),
                        "learned": np.concatenate([s_xyz, xyz(out.predicted)])}
                counts = score_maps(maps, truth, tree, mapper.grid, region, scene.bounds_m,
                                    deltas)
                for key, c in counts.items():
                    total.setdefault(key, Counts()).add(c)
    return total


def _fmt(v: float | None) -> str:
    return "–" if v is None else f"{v:.3f}"


def table(cfg: EvalModelConfig, totals: dict[tuple[str, int, str], Counts]) -> str:
    """Markdown: one row per (region, method), P / R / F at each tolerance."""
    head = "| region | map | " + " | ".join(
        f"P@{d:g} | R@{d:g} | F@{d:g}" for d in cfg.delta_fracs) + " |"
    rule = "|---|---|" + "---|---|---|" * len(cfg.delta_fracs)
    rows = [head, rule]
    for region in REGIONS:
        for m in METHODS:
            cells = []
            for di in range(len(cfg.delta_fracs)):
                s = totals[(m, di, region)].scores()
                cells += [_fmt(s["precision"]), _fmt(s["recall"]), _fmt(s["f"])]
            rows.append(f"| {region} | {m} | " + " | ".join(cells) + " |")
    return "\n".join(rows) + "\n"


def main(cfg: EvalModelConfig) -> int:
    import torch
    from tqdm import tqdm

    from mapper.model import load_checkpoint
    from rovergate.logs import init_logging
    init_logging("eval-model")
    torch.set_num_threads(cfg.threads)
    checkpoint = load_checkpoint(cfg.checkpoint or None)
    t0 = time.perf_counter()
    totals: dict[tuple[str, int, str], Counts] = {}
    per_scene = {}
    for i, name in enumerate(tqdm(cfg.scenes, desc="eval-model", unit="scene")):
        counts = evaluate_scene(cfg, name, i, checkpoint)
        per_scene[name] = {f"{m}/{cfg.delta_fracs[di]:g}/{r}": c.scores()
                           for (m, di, r), c in counts.items()}
        for key, c in counts.items():
            totals.setdefault(key, Counts()).add(c)
    md = table(cfg, totals)
    cfg.out.mkdir(parents=True, exist_ok=True)
    (cfg.out / "table.md").write_text(md)
    (cfg.out / "results.json").write_text(json.dumps({
        "checkpoint": str(checkpoint.path), "config": {k: str(v) for k, v in vars(cfg).items()},
        "pooled": {f"{m}/{cfg.delta_fracs[di]:g}/{r}": c.scores()
                   for (m, di, r), c in totals.items()},
        "per_scene": per_scene, "seconds": round(time.perf_counter() - t0, 1)}, indent=1) + "\n")
    print(md, end="")
    print(f"({len(cfg.scenes)} scenes x {len(cfg.platforms)} platforms x {cfg.walks} walks, "
          f"scored at steps {', '.join(map(str, cfg.score_at))}; delta as a fraction of "
          f"d_scene; {time.perf_counter() - t0:.0f} s; written to {cfg.out})")
    return 0
