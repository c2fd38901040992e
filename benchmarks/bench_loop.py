"""Benchmark: per-stage step times, and the process set against the in-process loop.

Runs the same 20-step mission (same seed) alternately in process and as the process set over
Zenoh, several rounds in one program so both see the same machine load, and prints medians and
ratios. Usage: .venv/bin/python benchmarks/bench_loop.py [--steps 20] [--rounds 3]
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import statistics
import tempfile
import time
from pathlib import Path

from mission.runtime.loop import run_in_process, run_processes
from rover_sim.catalog import resolve_scene
from rovergate.config import MissionConfig
from rovergate.runtime import tune_allocator

STAGES = ("render", "integrate", "gate", "plan", "execute")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=20)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--condition", default="obs")
    args = ap.parse_args()
    tune_allocator()  # as every rovergate program does (rovergate/runtime.py)
    logging.basicConfig(level=logging.WARNING)
    tmp = Path(tempfile.mkdtemp(prefix="rovergate-bench-"))
    base = MissionConfig(steps=args.steps, condition=args.condition, progress=False)
    resolve_scene(base.scene)
    rows: dict[str, list] = {"in-process": [], "processes": []}
    for r in range(args.rounds):
        for mode, fn in (("in-process", run_in_process), ("processes", run_processes)):
            cfg = dataclasses.replace(base, out=tmp / f"{mode}-{r}")
            t0 = time.perf_counter()
            rec = fn(cfg)
            total = time.perf_counter() - t0
            rows[mode].append((total, sum(rec.step_wall_s), rec))
            print(f"round {r} {mode:>10}: {total:6.2f} s total, "
                  f"{sum(rec.step_wall_s):6.2f} s in the loop, final coverage "
                  f"{rec.coverage[-1]:.4f}", flush=True)

    print(f"\nmission: {base.scene.name}/{base.start}, {args.steps} steps, condition "
          f"{args.condition}, {args.rounds} rounds per mode")
    print(f"{'stage (median s/step)':<24}{'in-process':>12}{'processes':>12}")
    for stage in STAGES:
        med = [statistics.median(v for _, _, rec in rows[m] for v in rec.stage_s.get(stage, []))
               for m in ("in-process", "processes")]
        print(f"{stage:<24}{med[0]:>12.4f}{med[1]:>12.4f}")
    for label, key in (("transport and glue", "median_transport_s"),
                       ("whole step", "median_step_s")):
        med = [statistics.median(rec.metrics()[key] for _, _, rec in rows[m])
               for m in ("in-process", "processes")]
        print(f"{label:<24}{med[0]:>12.4f}{med[1]:>12.4f}")
    loop = {m: statistics.median(w for _, w, _ in rows[m]) for m in rows}
    total = {m: statistics.median(t for t, _, _ in rows[m]) for m in rows}
    print(f"\nloop wall time (steps only): in-process {loop['in-process']:.2f} s, processes "
          f"{loop['processes']:.2f} s, ratio {loop['processes'] / loop['in-process']:.3f}")
    print(f"total wall time (with start-up and shutdown): in-process "
          f"{total['in-process']:.2f} s, processes {total['processes']:.2f} s, ratio "
          f"{total['processes'] / total['in-process']:.3f}")
    startup = {m: statistics.median(t - w for t, w, _ in rows[m]) for m in rows}
    print(f"start-up and shutdown (total minus loop): in-process {startup['in-process']:.2f} s, "
          f"processes {startup['processes']:.2f} s, the process set's extra "
          f"{startup['processes'] - startup['in-process']:.2f} s")
    same = all(rows["processes"][i][2].coverage == rows["in-process"][i][2].coverage
               for i in range(args.rounds))
    print(f"identical per-step coverage in both modes: {same}")


if __name__ == "__main__":
    main()
