"""Benchmark: what the flight recorder costs a mission, and how big its bag is.

Runs the same mission (same seed: the same messages) with the recorder off, with zstd
chunks, and with uncompressed chunks, several rounds alternating between the three, and
prints the median step wall time of each (the loop's own clock: from one step's tick to the
next), the ratio to the unrecorded run, the writer's seconds per step (in its own process),
and the bag's size per 100 steps. In process, every message is encoded for the
recorder on the loop's thread (the process set has the bytes already); in the process set
(``--processes``) the mission manager gets the bytes from its subscriptions.

Usage: .venv/bin/python benchmarks/bench_recorder.py [--steps 60] [--rounds 3] [--processes]
           [--platform rover]
"""

from __future__ import annotations

import argparse
import logging
import statistics
import tempfile
from pathlib import Path

from mission.runtime.loop import run_in_process, run_processes
from rover_sim.catalog import resolve_scene
from rovergate.config import MissionConfig
from rovergate.runtime import tune_allocator

SETTINGS = {"off": dict(record=False),
            "zstd": dict(record=True, record_compression="zstd"),
            "none": dict(record=True, record_compression="none")}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=60)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--platform", default="rover")
    ap.add_argument("--processes", action="store_true",
                    help="run the process set (default: in process)")
    args = ap.parse_args()
    logging.basicConfig(level=logging.WARNING)
    tune_allocator()
    steps_s: dict[str, list[float]] = {k: [] for k in SETTINGS}
    writer_s: dict[str, list[float]] = {k: [] for k in SETTINGS}
    mb100: dict[str, list[float]] = {k: [] for k in SETTINGS}
    with tempfile.TemporaryDirectory() as tmp:
        for r in range(args.rounds):
            for name, settings in SETTINGS.items():
                cfg = MissionConfig(steps=args.steps, platform=args.platform, progress=False,
                                    out=Path(tmp) / f"{name}-{r}", in_process=not args.processes,
                                    **settings)
                resolve_scene(cfg.scene)
                record = (run_processes(cfg) if args.processes else run_in_process(cfg))
                steps_s[name].append(statistics.median(record.step_wall_s))
                rec = record.recording
                if rec:
                    writer_s[name].append(rec["write_s"] / args.steps)
                    mb100[name].append(rec["file_bytes"] / 1e6 * 100 / args.steps)
                print(f"round {r} {name}: median step {steps_s[name][-1]:.4f} s"
                      + (f", bag {rec['file_bytes'] / 1e6:.1f} MB" if rec else ""), flush=True)
    base = statistics.median(steps_s["off"])
    mode = "process set" if args.processes else "in process"
    print(f"\n{args.platform}, {mode}, {args.steps} steps, {args.rounds} rounds "
          f"(medians over rounds)")
    print("| recorder | median step s | ratio to off | writer s/step | MB per 100 steps |")
    print("|---|---|---|---|---|")
    for name in SETTINGS:
        step = statistics.median(steps_s[name])
        w = f"{statistics.median(writer_s[name]):.4f}" if writer_s[name] else "—"
        mb = f"{statistics.median(mb100[name]):.0f}" if mb100[name] else "—"
        print(f"| {name} | {step:.4f} | {step / base:.3f} | {w} | {mb} |")


if __name__ == "__main__":
    main()
