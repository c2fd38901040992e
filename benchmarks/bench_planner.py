"""Benchmark: the planner's step with its defaults (beam search) against the greedy planner.

For each platform, one program runs the same in-process mission (``arch_field/a``, condition
``learned``, one torch thread as a study worker has) with the beam planner and with the greedy
one, alternating, and prints the median plan time per step, the median whole step, and the
ratio beam / greedy. Target: the beam's median plan step under 2 s on the 2-core CPU.

Usage: .venv/bin/python benchmarks/bench_planner.py [--steps 40] [--rounds 1]
"""

from __future__ import annotations

import argparse
import logging
import statistics

import torch

from mission.runtime.loop import run_in_process
from rover_sim.catalog import resolve_scene
from rovergate.config import MissionConfig
from rovergate.runtime import tune_allocator


def mission(platform: str, planner: str, steps: int) -> dict:
    cfg = MissionConfig(platform=platform, condition="learned", steps=steps, progress=False,
                        in_process=True)
    cfg.planner.name = planner
    resolve_scene(cfg.scene)
    record = run_in_process(cfg)
    return {"plan": record.stage_s["plan"], "step": record.step_wall_s,
            "coverage": record.coverage[-1]}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=40)
    ap.add_argument("--rounds", type=int, default=1)
    args = ap.parse_args()
    tune_allocator()  # as every rovergate program does (rovergate/runtime.py)
    torch.set_num_threads(1)
    logging.getLogger().setLevel(logging.WARNING)
    print(f"{args.steps}-step missions, arch_field/a, learned, {args.rounds} round(s); "
          "medians over every step of every round")
    print(f"{'platform':8} {'planner':7} {'plan s':>8} {'step s':>8} {'coverage':>9}")
    for platform in ("flyer", "rover"):
        plan: dict[str, list[float]] = {"beam": [], "greedy": []}
        step: dict[str, list[float]] = {"beam": [], "greedy": []}
        cov: dict[str, float] = {}
        for _ in range(args.rounds):
            for planner in ("beam", "greedy"):
                r = mission(platform, planner, args.steps)
                plan[planner] += r["plan"]
                step[planner] += r["step"]
                cov[planner] = r["coverage"]
        for planner in ("beam", "greedy"):
            print(f"{platform:8} {planner:7} {statistics.median(plan[planner]):8.3f} "
                  f"{statistics.median(step[planner]):8.3f} {cov[planner]:9.3f}")
        print(f"{platform:8} ratio beam / greedy, plan step: "
              f"{statistics.median(plan['beam']) / statistics.median(plan['greedy']):.2f}")


if __name__ == "__main__":
    main()
