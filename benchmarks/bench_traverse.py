"""Benchmark: the rover's traversability layer, per step (the planner's `traverse` stage).

Runs one in-process rover mission (``--scene``, start a, ``--steps``, `obs`) and keeps what
the planner received at every step (mast frame, hazard cameras, base pose); then replays those
steps into a fresh layer ``--repeats`` times, timing each step's work: taking in the frames
(``add_step``) and building the step's masks (``prepare``). Prints the median per step of
each part and of both, over all steps and repeats, and their ratio to the issue's budget of
20 ms. Run it under ``ONEDNN_MAX_CPU_ISA=AVX2 ATEN_CPU_CAPABILITY=avx2`` too (the layer is
numpy and scipy; the caps change nothing it calls, which this shows).

Usage: .venv/bin/python benchmarks/bench_traverse.py [--scene arch_field] [--steps 40]
           [--repeats 5]
"""

from __future__ import annotations

import argparse
import logging
import statistics
import tempfile
import time
from pathlib import Path

from rovergate.runtime import tune_allocator

BUDGET_MS = 20.0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default="arch_field")
    ap.add_argument("--steps", type=int, default=40)
    ap.add_argument("--repeats", type=int, default=5)
    args = ap.parse_args()
    tune_allocator()
    logging.basicConfig(level=logging.ERROR)
    from mission.runtime.loop import run_in_process
    from planner.logic import PlannerLogic
    from planner.traversability import TerrainMap
    from rover_sim.catalog import resolve_scene
    from rovergate.config import MissionConfig
    cfg = MissionConfig(platform="rover", start="a", steps=args.steps, condition="obs",
                        in_process=True, progress=False,
                        out=Path(tempfile.mkdtemp(prefix="rovergate-bench-traverse-")))
    cfg.scene.name = args.scene
    resolve_scene(cfg.scene)
    kept: list[tuple[int, dict]] = []
    restore = PlannerLogic.restore

    def keep(self, step, inputs):
        kept.append((step, dict(inputs)))
        return restore(self, step, inputs)

    PlannerLogic.restore = keep
    try:
        run_in_process(cfg)
    finally:
        PlannerLogic.restore = restore
    add, prep = [], []
    for _ in range(args.repeats):
        terrain = TerrainMap(cfg)
        for step, i in kept:
            t0 = time.perf_counter()
            terrain.add_step(step, i["base"].matrix(),
                             (i["pose"].matrix(), i["info"], i["depth"]),
                             {"front": i["front"], "rear": i["rear"]})
            t1 = time.perf_counter()
            x, y = i["base"].position[:2]
            terrain.prepare(float(x), float(y))
            t2 = time.perf_counter()
            add.append(1000 * (t1 - t0))
            prep.append(1000 * (t2 - t1))
    both = [a + p for a, p in zip(add, prep, strict=True)]
    print(f"{args.scene}/a, {len(kept)} steps x {args.repeats} repeats "
          f"({terrain.shape[0]} x {terrain.shape[1]} cells of {cfg.traverse.cell_m} m)")
    print(f"frames in (add_step): median {statistics.median(add):.2f} ms")
    print(f"masks (prepare):      median {statistics.median(prep):.2f} ms")
    print(f"layer per step:       median {statistics.median(both):.2f} ms "
          f"({statistics.median(both) / BUDGET_MS:.2f} of the {BUDGET_MS:.0f} ms budget)")


if __name__ == "__main__":
    main()
