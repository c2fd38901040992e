"""Benchmark: the mapper's cost per step with the learned occupancy, and its memory.

1. In one process, a rover mission on arch_field in the ``learned`` condition (30 steps): the
   median of the mapper's whole step (depth into S_t, depth into the occupancy grid, the
   model on the window, the prediction's points), and of each part, timed on the same frames.
   The same mission in ``obs`` (no model) gives the ratio.
2. The process set, ``learned``, 15 steps: the mapper process's median step and its peak
   resident memory (from its log).

Usage: .venv/bin/python benchmarks/bench_mapper.py [--steps 30]
"""

from __future__ import annotations

import argparse
import json
import logging
import re
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from mapper.integrate import backproject
from mapper.mapper import Mapper
from mission.loop import run_in_process
from rover_sim.catalog import resolve_scene
from rover_sim.sim import RoverSim
from rovergate.config import MissionConfig
from rovergate.runtime import tune_allocator


def mission(condition: str, steps: int, out: Path) -> MissionConfig:
    cfg = MissionConfig(condition=condition, steps=steps, in_process=True, progress=False)
    cfg.out = str(out)
    resolve_scene(cfg.scene)
    return cfg


def parts(cfg: MissionConfig, poses: list) -> dict[str, list[float]]:
    """Times of each part of the mapper's step, over the frames of ``poses``."""
    sim = RoverSim(cfg)
    mapper = Mapper.for_mission(cfg)
    times: dict[str, list[float]] = {"surface": [], "grid": [], "model": [], "points": []}
    try:
        for t, state in enumerate(poses):
            sim.state = state
            f = sim.render(t)
            T = f.T_map_camera.matrix()
            t0 = time.perf_counter()
            returns = backproject(f.depth_m, f.intrinsics, T)
            mapper.surface.integrate(returns)
            t1 = time.perf_counter()
            mapper.grid.integrate(f.depth_m, f.intrinsics, T, returns_map=returns)
            t2 = time.perf_counter()
            mapper.predictor.update(T[:3, 3])
            t3 = time.perf_counter()
            mapper.predictor.predicted()
            t4 = time.perf_counter()
            for k, v in zip(times, (t1 - t0, t2 - t1, t3 - t2, t4 - t3), strict=True):
                times[k].append(v)
    finally:
        sim.close()
    return times


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=30)
    args = ap.parse_args()
    tune_allocator()  # as every rovergate program does (rovergate/runtime.py)
    logging.basicConfig(level=logging.WARNING)
    print(f"torch {torch.__version__}, {torch.get_num_threads()} threads")
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        med = {}
        for condition in ("obs", "learned"):
            rec = run_in_process(mission(condition, args.steps, tmp / condition))
            med[condition] = statistics.median(rec.stage_s["integrate"])
            print(f"in process, {condition:8s}: mapper step median {1000 * med[condition]:6.1f} ms"
                  f" over {args.steps + 1} frames (max "
                  f"{1000 * max(rec.stage_s['integrate']):.0f} ms)")
            if condition == "learned":
                poses = [(x, y, 0.0) for x, y in rec.base_xy]
                yaws = [float(np.arctan2(b[1] - a[1], b[0] - a[0]))
                        for a, b in zip(rec.base_xy, rec.base_xy[1:], strict=False)]
                poses = [(x, y, yw) for (x, y, _), yw in zip(poses, [0.0, *yaws], strict=True)]
                split = parts(mission(condition, args.steps, tmp / "parts"), poses)
                print("  parts (median ms): " + ", ".join(
                    f"{k} {1000 * statistics.median(v):.1f}" for k, v in split.items()))
        print(f"ratio learned / obs: {med['learned'] / med['obs']:.1f}")
        out = tmp / "procs"
        r = subprocess.run([sys.executable, "-m", "mission.cli", "run", "--condition",
                            "learned", "--steps", "15", "--no-progress", "--out", str(out)],
                           capture_output=True, text=True, timeout=600)
        if r.returncode != 0:
            raise SystemExit(f"process-set mission failed:\n{r.stderr[-2000:]}")
        metrics = json.loads((out / "metrics.json").read_text())
        log = (out / "logs" / "mapper.log").read_text()
        peak = re.findall(r"peak resident memory (\d+) MB", log)
        print(f"process set, learned : mapper step median "
              f"{1000 * metrics['median_stage_s']['integrate']:.1f} ms; mapper process peak "
              f"resident memory {peak[-1] if peak else '?'} MB")


if __name__ == "__main__":
    main()
