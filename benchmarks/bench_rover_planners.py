"""Benchmark: the rover's planners (and its sensing choices) over the suite's scenes, starts and
seeds, with how each run drove.

Each (setting, scene, start, condition, seed) is one in-process mission of ``--steps`` steps;
``--workers`` of them run at once (each in its own process, one thread each). Prints every
run's final coverage, collisions, stuck steps and metres driven, then per scene and condition
the mean C_T of each setting, its mean paired difference from the first setting's (the same
start, condition and seed) with the pairs' spread (min to max) and how many pairs it lost,
and the failure counts; last, the same pooled over every scene.

Settings: `greedy`; `beam` (straight first motions only); `beam-routed`
(--planner.route-blocked); `beam-routed-0.5` (also --planner.beam-discount 0.5);
`greedy-mast-only` and `beam-routed-mast-only` (--hazcam.no-feed-map: the hazard cameras
feed the traversability layer only, not S_t).

Usage: .venv/bin/python benchmarks/bench_rover_planners.py [--scenes arch_field ...]
           [--starts a b c d e] [--seeds 0 1 2] [--conditions obs]
           [--settings greedy beam-routed] [--steps 100] [--workers 2]
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import os
import statistics
import tempfile
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

from rover_sim.catalog import SUITE

SETTINGS: dict[str, dict[str, dict]] = {
    "greedy": {"planner": {"name": "greedy"}},
    "beam": {"planner": {"name": "beam"}},
    "beam-routed": {"planner": {"name": "beam", "route_blocked": True}},
    "beam-routed-0.5": {"planner": {"name": "beam", "route_blocked": True,
                                    "beam_discount": 0.5}},
    "greedy-mast-only": {"planner": {"name": "greedy"}, "hazcam": {"feed_map": False}},
    "beam-routed-mast-only": {"planner": {"name": "beam", "route_blocked": True},
                              "hazcam": {"feed_map": False}},
}


def one_run(job: tuple[str, str, str, str, int, int]) -> dict:
    """One mission in this (worker) process: its figures."""
    setting, scene, start, condition, seed, steps = job
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    from mission.runtime.loop import run_in_process
    from rover_sim.catalog import resolve_scene
    from rovergate.config import MissionConfig
    logging.basicConfig(level=logging.ERROR)
    cfg = MissionConfig(platform="rover", start=start, steps=steps, seed=seed,
                        condition=condition, in_process=True, progress=False,
                        out=Path(tempfile.mkdtemp(prefix="rovergate-bench-rover-")))
    cfg.scene.name = scene
    for section, fields in SETTINGS[setting].items():
        setattr(cfg, section, dataclasses.replace(getattr(cfg, section), **fields))
    resolve_scene(cfg.scene)
    m = run_in_process(cfg).metrics()
    return {"setting": setting, "scene": scene, "start": start, "condition": condition,
            "seed": seed, "c_t": m["coverage"][-1], "collisions": m["collisions"],
            "stuck": m["stuck_steps"], "driven": m["path_length_m"],
            "traverse_s": m["median_stage_s"].get("traverse", 0.0)}


def summary(rows: list[dict], settings: list[str], label: str) -> None:
    base = settings[0]
    keyed = {(r["setting"], r["start"], r["condition"], r["seed"], r["scene"]): r for r in rows}
    cells = []
    for s in settings:
        mine = [r for r in rows if r["setting"] == s]
        if not mine:
            continue
        mean = statistics.mean(r["c_t"] for r in mine)
        text = f"{mean:.3f}"
        if s != base:
            diffs = [r["c_t"] - keyed[(base, r["start"], r["condition"], r["seed"],
                                       r["scene"])]["c_t"] for r in mine
                     if (base, r["start"], r["condition"], r["seed"], r["scene"]) in keyed]
            if diffs:
                text += (f" {statistics.mean(diffs):+.3f} [{min(diffs):+.2f}, {max(diffs):+.2f}]"
                         f" lost {sum(d < 0 for d in diffs)}/{len(diffs)}")
        text += (f"; {sum(r['collisions'] for r in mine)} coll, "
                 f"{sum(r['stuck'] for r in mine)} stuck, "
                 f"min {min(r['driven'] for r in mine):.0f} m")
        cells.append(f"{s}: {text}")
    print(f"{label:24} " + " | ".join(cells))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", nargs="+", default=list(SUITE))
    ap.add_argument("--starts", nargs="+", default=list("abcde"))
    ap.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    ap.add_argument("--conditions", nargs="+", default=["obs"])
    ap.add_argument("--settings", nargs="+", default=["greedy", "beam-routed"],
                    choices=list(SETTINGS))
    ap.add_argument("--steps", type=int, default=100)
    ap.add_argument("--workers", type=int, default=2)
    args = ap.parse_args()
    jobs = [(s, sc, st, c, seed, args.steps) for sc in args.scenes for st in args.starts
            for c in args.conditions for seed in args.seeds for s in args.settings]
    print(f"rover, {len(jobs)} runs: scenes {' '.join(args.scenes)}, starts "
          f"{' '.join(args.starts)}, {' '.join(args.conditions)}, seeds {args.seeds}, "
          f"{args.steps} steps, {args.workers} workers", flush=True)
    rows = []
    with ProcessPoolExecutor(args.workers) as pool:
        for r in pool.map(one_run, jobs):
            rows.append(r)
            print(f"{r['scene']:11} {r['start']} {r['condition']:8} {r['setting']:22} seed "
                  f"{r['seed']}: C_T {r['c_t']:.3f}, {r['collisions']} collisions, "
                  f"{r['stuck']} stuck, {r['driven']:.1f} m, traverse "
                  f"{1000 * r['traverse_s']:.1f} ms", flush=True)
    print(f"\nmean C_T; paired difference from {args.settings[0]} (mean [min, max], pairs "
          "lost); collisions, stuck steps, least driven")
    for scene in args.scenes:
        for c in args.conditions:
            summary([r for r in rows if r["scene"] == scene and r["condition"] == c],
                    args.settings, f"{scene} {c}")
    for c in args.conditions:
        summary([r for r in rows if r["condition"] == c], args.settings, f"all scenes {c}")
    ms = sorted(1000 * r["traverse_s"] for r in rows)
    print(f"traversability layer, median per step: {statistics.median(ms):.1f} ms "
          f"(runs' medians from {ms[0]:.1f} to {ms[-1]:.1f} ms)")


if __name__ == "__main__":
    main()
