"""`rovergate train`: build the training set from procedural worlds and train the model.

Training worlds come from the suite's generators with seeds from :data:`TRAIN_SEED_BASE` up,
disjoint from every evaluation scene's seed (:func:`check_disjoint`). In each world a rover
walk and a flyer walk (:mod:`mission.learning.walks`) are integrated into the mapper's voxel
grid exactly as in a mission; every few steps the window around the camera is stored with its
labels (the voxels the true surface passes through). Everything is seeded: with the same torch
version and thread count, the run reproduces the shipped checkpoint bit for bit.
"""

from __future__ import annotations

import json
import logging
import multiprocessing as mp
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np
import torch
from torch.nn import functional as F

from mapper.grid import GridSpec, OccupancyGrid
from mapper.model import (
    OccupancyNet,
    WindowSpec,
    crop,
    encode,
    file_sha256,
    save_checkpoint,
    weights_sha256,
)
from mission.learning.walks import random_sensing, walk
from rover_sim import suite
from rover_sim.scene import Scene
from rovergate.errors import ConfigError

log = logging.getLogger("rovergate.train")

#: The generators training worlds are drawn from, in turn.
FAMILIES = {
    "arch_field": suite.build_arch_field,
    "crater": suite.build_crater,
    "canyon": suite.build_canyon,
    "lava_tube": suite.build_lava_tube,
    "outpost": suite.build_outpost,
    "ruins": suite.build_ruins,
}
#: Training world i uses seed TRAIN_SEED_BASE + i; validation worlds start at VAL_SEED_BASE.
TRAIN_SEED_BASE = 1000
VAL_SEED_BASE = 5000
IGNORE = 2
"""Label of voxels the loss ignores: those outside the grid, where a window overhangs it."""


@dataclass
class TrainConfig:
    """Reproduce the shipped occupancy checkpoint (defaults, written to runs/train/), or train
    a variant."""

    out: Path = Path("runs/train/occupancy.pt")
    """Where to write the checkpoint (a JSON summary goes beside it). Not the shipped model by
    default, so that a trial run cannot destroy it: to replace it, pass its path explicitly
    (--out mapper/weights/occupancy.pt in a source checkout); to use another checkpoint in a
    mission, --mapper.checkpoint PATH."""
    worlds: int = 36
    """Training worlds, cycling through the six generators."""
    val_worlds: int = 6
    """Validation worlds (other seeds), for the loss and F-score the model card reports."""
    walk_steps: int = 24
    """Poses per walk; a rover walk and a flyer walk per world."""
    snapshot_every: int = 3
    """Store a training window every this many poses of a walk."""
    iterations: int = 2000
    """Optimiser steps."""
    batch: int = 6
    """Windows per optimiser step."""
    crop: tuple[int, int, int] = (40, 40, 32)
    """Training crop of the 64 x 64 x 32 window, in voxels (the model is convolutional)."""
    lr: float = 2e-3
    """Adam learning rate (cosine decay to a twentieth of it)."""
    pos_weight: float = 4.0
    """Weight of surface voxels in the loss (they are 5% of the window). It sets where the
    mapper's fixed 0.5 threshold falls between recall and precision: 2 gave the better
    precision but no more recall than the geometric baseline in unobserved space."""
    seed: int = 0
    """Seed of the walks' choices, the crops, the augmentations and the initial weights."""
    threads: int = 2
    """Torch threads and data-gathering worker processes. The result depends on it."""
    device: str = "cpu"
    """cpu, or cuda where a GPU is present (faster, not bit-identical to the CPU run)."""
    label_samples: int = 400_000
    """True surface samples per world for the labels (over the grid's 50 m x 50 m)."""


# ----------------------------------------------------------------------------- data

def check_disjoint() -> None:
    """Training and validation seeds never meet an evaluation scene's seed."""
    import inspect
    eval_seeds = {inspect.signature(b).parameters["seed"].default for b in FAMILIES.values()}
    assert all(s < TRAIN_SEED_BASE for s in eval_seeds), eval_seeds


def world(index: int, seed_base: int = TRAIN_SEED_BASE) -> Scene:
    """Training (or validation) world ``index``: family index mod 6, seed base + index."""
    build = list(FAMILIES.values())[index % len(FAMILIES)]
    return build(seed=seed_base + index)


def surface_labels(scene: Scene, spec: GridSpec, n: int, seed: int) -> np.ndarray:
    """(nx, ny, nz) uint8 over the whole grid: 1 where the true surface passes, else 0.

    The surface is sampled over the grid's whole footprint, not only the box of interest, so
    every voxel the camera can see has a label (where a scene's geometry ends, the render shows
    nothing and the label is empty too)."""
    lo = np.asarray(spec.origin_m)
    hi = lo + np.asarray(spec.shape) * spec.voxel_m
    everywhere = replace(scene, bounds_m=(*lo, *hi))
    labels = np.zeros(spec.shape, dtype=np.uint8)
    ijk, inside = spec.index(everywhere.surface_samples(n, seed=seed))
    labels[tuple(ijk[inside].T)] = 1
    return labels


def gather_world(args: tuple[int, int, TrainConfig, WindowSpec]) -> list[np.ndarray]:
    """The (2, X, Y, Z) uint8 [state, label] windows of one world's two walks."""
    index, seed_base, cfg, window = args
    scene = world(index, seed_base)
    spec = GridSpec.around(scene.bounds_m, window.voxel_m)
    labels = surface_labels(scene, spec, cfg.label_samples, seed=seed_base + index)
    out = []
    for p, platform in enumerate(("rover", "flyer")):
        walk_seed = cfg.seed * 1_000_003 + (seed_base + index) * 2 + p
        rng = np.random.default_rng(walk_seed)
        sensing = random_sensing(rng) if rng.random() < 0.4 else None
        grid = OccupancyGrid(spec)
        for frame in walk(scene, platform, cfg.walk_steps, walk_seed, sensing):
            grid.integrate(frame.depth_m, frame.intrinsics, frame.T_map_camera)
            if frame.step % cfg.snapshot_every == cfg.snapshot_every - 1:
                start = window.start(spec, frame.T_map_camera[:3, 3])
                out.append(np.stack([crop(grid.state, start, window.size),
                                     crop(labels, start, window.size, fill=IGNORE)]))
    return out


def gather(cfg: TrainConfig, window: WindowSpec, n_worlds: int, seed_base: int,
           what: str) -> np.ndarray:
    """(N, 2, X, Y, Z) uint8 windows of ``n_worlds`` worlds, in world order."""
    from tqdm import tqdm
    jobs = [(i, seed_base, cfg, window) for i in range(n_worlds)]
    windows: list[np.ndarray] = []
    if cfg.threads > 1:
        with mp.get_context("spawn").Pool(cfg.threads) as pool:
            for w in tqdm(pool.imap(gather_world, jobs), total=len(jobs), desc=what,
                          unit="world"):
                windows.extend(w)
    else:
        for job in tqdm(jobs, desc=what, unit="world"):
            windows.extend(gather_world(job))
    return np.stack(windows)


# ----------------------------------------------------------------------------- training

def augment(sample: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """A random quarter turn and mirror about the vertical axis through the window centre."""
    out = np.rot90(sample, k=int(rng.integers(4)), axes=(1, 2))
    if rng.random() < 0.5:
        out = out[:, ::-1]
    return np.ascontiguousarray(out)


def make_batch(data: np.ndarray, idx: np.ndarray, window: WindowSpec,
               size: tuple[int, int, int], rng: np.random.Generator | None
               ) -> tuple[torch.Tensor, torch.Tensor]:
    """Encoded inputs (B, 8, *size) and labels (B, 1, *size) of windows ``idx``; with an rng,
    augmented and randomly cropped, else centre-cropped."""
    xs, ys = [], []
    for i in idx:
        s = augment(data[i], rng) if rng is not None else data[i]
        x = encode(s[0], window.below)
        lo = [(full - c) // 2 for full, c in zip(window.size, size, strict=True)]
        if rng is not None:
            lo = [int(rng.integers(full - c + 1)) for full, c in zip(window.size, size,
                                                                       strict=True)]
        sl = tuple(slice(a, a + c) for a, c in zip(lo, size, strict=True))
        xs.append(x[(slice(None), *sl)])
        ys.append(s[1][sl][None])
    return torch.from_numpy(np.stack(xs)), torch.from_numpy(np.stack(ys))


def masked_loss(logits: torch.Tensor, labels: torch.Tensor, pos_weight: float) -> torch.Tensor:
    """Weighted binary cross-entropy over the voxels whose label is known."""
    known = labels != IGNORE
    target = (labels == 1).float()
    w = torch.where(target > 0, torch.tensor(pos_weight), torch.tensor(1.0)) * known
    loss = F.binary_cross_entropy_with_logits(logits, target, weight=w, reduction="sum")
    return loss / known.sum().clamp(min=1)


@torch.no_grad()
def validate(model: OccupancyNet, data: np.ndarray, window: WindowSpec, pos_weight: float,
             device: str) -> dict[str, float]:
    """Loss, and voxel precision / recall / F-score at probability 0.5, over whole windows."""
    model.eval()
    loss, tp, fp, fn = 0.0, 0, 0, 0
    for i in range(len(data)):
        x, y = make_batch(data, np.array([i]), window, window.size, None)
        logits = model(x.to(device)).cpu()
        loss += float(masked_loss(logits, y, pos_weight))
        known = y != IGNORE
        pred = (logits >= 0) & known
        true = (y == 1) & known
        tp += int((pred & true).sum())
        fp += int((pred & ~true).sum())
        fn += int((~pred & true).sum())
    model.train()
    p = tp / max(tp + fp, 1)
    r = tp / max(tp + fn, 1)
    return {"loss": loss / max(len(data), 1), "voxel_precision": p, "voxel_recall": r,
            "voxel_f": 2 * p * r / max(p + r, 1e-12)}


def train(cfg: TrainConfig, data: np.ndarray, val: np.ndarray, window: WindowSpec,
          progress: bool = True) -> tuple[OccupancyNet, dict]:
    """Train from scratch on ``data``; returns the model and its loss history."""
    from tqdm import tqdm
    torch.manual_seed(cfg.seed)
    rng = np.random.default_rng([cfg.seed, 1])
    model = OccupancyNet().to(cfg.device)
    opt = torch.optim.Adam(model.parameters(), lr=cfg.lr)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, cfg.iterations,
                                                       eta_min=cfg.lr / 20)
    history: dict[str, list] = {"iteration": [], "train_loss": [], "val": []}
    running = []
    bar = tqdm(range(cfg.iterations), desc="train", unit="it", disable=not progress)
    for it in bar:
        idx = rng.integers(len(data), size=cfg.batch)
        x, y = make_batch(data, idx, window, cfg.crop, rng)
        loss = masked_loss(model(x.to(cfg.device)), y.to(cfg.device), cfg.pos_weight)
        opt.zero_grad()
        loss.backward()
        opt.step()
        sched.step()
        running.append(loss.item())
        last = it + 1 == cfg.iterations
        if (it + 1) % 100 == 0 or last:
            history["iteration"].append(it + 1)
            history["train_loss"].append(float(np.mean(running)))
            running = []
            if len(val) and ((it + 1) % 500 == 0 or last):
                history["val"].append({"iteration": it + 1,
                                       **validate(model, val, window, cfg.pos_weight,
                                                  cfg.device)})
            bar.set_postfix(loss=f"{history['train_loss'][-1]:.4f}")
    return model.cpu().eval(), history


def main(cfg: TrainConfig) -> int:
    """Gather, train, save; prints where the checkpoint went and its figures."""
    from rovergate.logs import init_logging
    init_logging("train")
    check_disjoint()
    if cfg.device == "cuda" and not torch.cuda.is_available():
        raise ConfigError("--device cuda: no CUDA device here; use --device cpu")
    torch.set_num_threads(cfg.threads)
    torch.use_deterministic_algorithms(True, warn_only=cfg.device != "cpu")
    window = WindowSpec()
    log.info("training config: %s", json.dumps(asdict(cfg), default=str))
    t0 = time.perf_counter()
    data = gather(cfg, window, cfg.worlds, TRAIN_SEED_BASE, "training worlds")
    val = gather(cfg, window, cfg.val_worlds, VAL_SEED_BASE, "validation worlds")
    t_data = time.perf_counter() - t0
    pos = float((data[:, 1] == 1).sum() / max((data[:, 1] != IGNORE).sum(), 1))
    log.info("%d training windows, %d validation windows (%.1f%% surface voxels) in %.0f s",
             len(data), len(val), 100 * pos, t_data)
    t1 = time.perf_counter()
    model, history = train(cfg, data, val, window)
    t_train = time.perf_counter() - t1
    meta = {
        "data": {"families": list(FAMILIES), "train_worlds": cfg.worlds,
                 "train_seeds": [TRAIN_SEED_BASE, TRAIN_SEED_BASE + cfg.worlds - 1],
                 "val_worlds": cfg.val_worlds,
                 "val_seeds": [VAL_SEED_BASE, VAL_SEED_BASE + cfg.val_worlds - 1],
                 "train_windows": int(len(data)), "val_windows": int(len(val)),
                 "surface_voxel_share": pos},
        "training": {**{k: (str(v) if isinstance(v, Path) else v)
                        for k, v in asdict(cfg).items()},
                     "torch": str(torch.__version__),
                     "gather_s": round(t_data, 1), "train_s": round(t_train, 1)},
        "history": history,
    }
    save_checkpoint(cfg.out, model, window, meta)
    summary = cfg.out.with_suffix(".json")
    summary.write_text(json.dumps({**meta, "sha256": file_sha256(cfg.out),
                                   "weights_sha256": weights_sha256(model)}, indent=1) + "\n")
    final = history["val"][-1] if history["val"] else {}
    print(f"checkpoint: {cfg.out} ({cfg.out.stat().st_size / 1e6:.1f} MB), sha256 "
          f"{file_sha256(cfg.out)[:16]}, weights {weights_sha256(model)[:16]}; data "
          f"{t_data / 60:.1f} min, training {t_train / 60:.1f} min; validation "
          + ", ".join(f"{k} {v:.3f}" for k, v in final.items() if k != "iteration"))
    return 0
