"""Benchmark: the rover's planners on start `a` of the suite scenes, over several seeds.

Each (planner setting, scene, seed) is one in-process mission of ``--steps`` steps under
``--condition`` (default `obs`: no prediction, so the planner alone differs); prints every
run's final coverage and collisions, then per scene the mean over seeds of each setting, its
difference from the greedy planner's and the seeds' spread (max - min), the noise the
difference must clear. Settings: `greedy`; `beam` (straight first motions only); `beam-routed`
(--planner.route-blocked); `beam-routed-0.5` (also --planner.beam-discount 0.5).

Usage: .venv/bin/python benchmarks/bench_rover_planners.py [--scenes arch_field ...]
           [--seeds 0 1 2] [--settings greedy beam-routed beam-routed-0.5] [--steps 100]
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import statistics
import tempfile
from pathlib import Path

from mission.loop import run_in_process
from rover_sim.catalog import SUITE, resolve_scene
from rovergate.config import MissionConfig
from rovergate.runtime import tune_allocator

SETTINGS = {
    "greedy": {"name": "greedy"},
    "beam": {"name": "beam"},
    "beam-routed": {"name": "beam", "route_blocked": True},
    "beam-routed-0.5": {"name": "beam", "route_blocked": True, "beam_discount": 0.5},
}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", nargs="+", default=list(SUITE))
    ap.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    ap.add_argument("--settings", nargs="+", default=["greedy", "beam-routed",
                                                      "beam-routed-0.5"],
                    choices=list(SETTINGS))
    ap.add_argument("--steps", type=int, default=100)
    ap.add_argument("--condition", default="obs")
    args = ap.parse_args()
    tune_allocator()
    logging.basicConfig(level=logging.ERROR)
    out = Path(tempfile.mkdtemp(prefix="rovergate-bench-rover-"))
    cover: dict[tuple[str, str], list[float]] = {}
    print(f"rover, start a, {args.steps} steps, {args.condition}, seeds {args.seeds}")
    for scene in args.scenes:
        for setting in args.settings:
            for seed in args.seeds:
                cfg = MissionConfig(platform="rover", start="a", steps=args.steps, seed=seed,
                                    condition=args.condition, in_process=True, progress=False,
                                    out=out)
                cfg.scene.name = scene
                cfg.planner = dataclasses.replace(cfg.planner, **SETTINGS[setting])
                resolve_scene(cfg.scene)
                rec = run_in_process(cfg)
                hits = sum(e.collided for e in rec.executions)
                cover.setdefault((scene, setting), []).append(rec.coverage[-1])
                print(f"{scene:11} {setting:16} seed {seed}: C_T {rec.coverage[-1]:.3f}, "
                      f"{hits} collisions", flush=True)
    print(f"\n{'scene':11} " + " ".join(f"{s:>24}" for s in args.settings))
    for scene in args.scenes:
        base = statistics.mean(cover[(scene, "greedy")]) if "greedy" in args.settings else None
        cells = []
        for s in args.settings:
            v = cover[(scene, s)]
            m = statistics.mean(v)
            diff = f" {m - base:+.3f}" if base is not None and s != "greedy" else ""
            cells.append(f"{m:.3f}{diff} (spread {max(v) - min(v):.2f})")
        print(f"{scene:11} " + " ".join(f"{c:>24}" for c in cells))
    print("(mean C_T over the seeds, its difference from greedy's mean, and the seeds' spread)")


if __name__ == "__main__":
    main()
