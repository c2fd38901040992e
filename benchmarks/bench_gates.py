"""Benchmark: each gate's compute time and memory on the same recorded inputs.

Runs one mission in process (under ``learned``: the prediction reaches the gate, and nothing
withheld changes the path), records every step's gate inputs (surface, prediction, pose with
its covariance, intrinsics, depth), then replays exactly those inputs through a fresh gate of
each condition, several rounds alternating between the conditions: the median and largest
time of a gate step, that median as a share of the mission's median step, what the gate
holds in memory after the last step (tracemalloc: the frames it keeps), and how many
predicted points it withheld over the mission. A gate step is the gate module's whole step:
counting every point's views (the planner's novelty, which the module computes under every
condition) and composing the map, then the filter. `learned` (no filter) is the reference
row, and the filter's own time (its frame and its test, timed inside the step) is given
apart.

With ``--blocks B`` it also prints each gate's median step in each of B equal blocks of
steps, and the last block's over the first's: whether a gate's step grows with the mission
(issue 30 asks that it follow what is new, not the whole map). ``--inputs FILE`` keeps the
recorded inputs (recorded once, read again on later runs), so that two trees replay the very
same steps: ``PYTHONPATH=OTHER_TREE`` runs this program against another tree's gate.

Usage: .venv/bin/python benchmarks/bench_gates.py [--steps 60] [--rounds 3]
           [--platform rover] [--degraded] [--blocks 5] [--inputs FILE] [--gates a,b]
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import pickle
import statistics
import tempfile
import time
import tracemalloc
from pathlib import Path

from gate.gate import Gate
from mission.runtime.loop import run_mission
from mission.runtime.transport import InProcessTransport
from rover_sim.catalog import resolve_scene
from rovergate.config import MissionConfig, SensingConfig
from rovergate.runtime import tune_allocator
from rovergate.types import MapperOutput

GATES = ("gated", "gated-ray", "gated-pose", "gated-split")
#: The reference: the same module step with no filter.
REFERENCE = "learned"


def record(cfg: MissionConfig) -> tuple[list[tuple], float]:
    """Every step's gate inputs, and the mission's median step time."""
    transport = InProcessTransport(cfg)
    inputs: list[tuple] = []
    start = transport.start

    def start_and_tap() -> None:
        start()
        node = transport.logic["gate"]
        handle = node.handle

        def tapped(step, given):
            pose = given["pose"]
            inputs.append((MapperOutput(step, given["surface"], given["predicted"]),
                           pose.pose, given["info"], given["depth"], pose.covariance))
            return handle(step, given)
        node.handle = tapped
    transport.start = start_and_tap
    rec = run_mission(cfg, transport)
    return inputs, statistics.median(rec.step_wall_s)


def _timed(obj, name: str, spent: list[float]) -> None:
    """Add the time of every call of ``obj.name`` to ``spent[-1]``."""
    method = getattr(obj, name, None)
    if method is None:
        return

    def timed(*a, **kw):
        t0 = time.perf_counter()
        try:
            return method(*a, **kw)
        finally:
            spent[-1] += time.perf_counter() - t0
    setattr(obj, name, timed)


def replay(cfg: MissionConfig, condition: str, inputs: list[tuple], trace: bool = False
           ) -> tuple[list[float], float, int, list[float]]:
    """(seconds per step, MB held after the last step (with ``trace`` only: tracing slows
    every allocation, so timed rounds run without it), predicted points withheld, seconds per
    step in the filter itself)."""
    if trace:
        tracemalloc.start()
    before = tracemalloc.get_traced_memory()[0] if trace else 0
    gate = Gate(condition, cfg.gate, cfg.sensor, cfg.scene.d_scene_m, cfg.scene.bounds_m,
                cfg.gate.view_tolerance_m)
    times, withheld, own = [], 0, []
    if gate.condition.withholds:
        for name in ("add_frame", "unsupported", "withheld"):
            _timed(gate.filter, name, own)
    for mapped, pose, info, depth, cov in inputs:
        own.append(0.0)
        t0 = time.perf_counter()
        out = gate.step(mapped, pose, info, depth, cov)
        times.append(time.perf_counter() - t0)
        withheld += out.suppressed
    held = 0.0
    if trace:
        held = (tracemalloc.get_traced_memory()[0] - before) / 2**20
        tracemalloc.stop()
    return times, held, withheld, own


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=60)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--platform", default="rover")
    ap.add_argument("--degraded", action="store_true",
                    help="blob dropout 0.1, noise 1%%, grazing 80 deg, drift 0.02 m and "
                         "0.3 deg per step")
    ap.add_argument("--blocks", type=int, default=0,
                    help="also print each gate's median step per block of steps")
    ap.add_argument("--inputs", type=Path,
                    help="the recorded inputs: read if the file exists, else recorded here")
    ap.add_argument("--gates", help="comma-separated conditions to replay (default: all)")
    args = ap.parse_args()
    tune_allocator()
    logging.basicConfig(level=logging.WARNING)
    sensing = (SensingConfig(noise_frac=0.01, dropout_blob_frac=0.1, grazing_max_deg=80.0,
                             drift_xy_m=0.02, drift_yaw_deg=0.3)
               if args.degraded else SensingConfig())
    cfg = MissionConfig(steps=args.steps, condition="learned", platform=args.platform,
                        sensing=sensing, progress=False,
                        out=Path(tempfile.mkdtemp(prefix="rovergate-bench-gates-")))
    resolve_scene(cfg.scene)
    if args.inputs is not None and args.inputs.exists():
        inputs, step_s = pickle.loads(args.inputs.read_bytes())  # our own file, just written
    else:
        inputs, step_s = record(cfg)
        if args.inputs is not None:
            args.inputs.write_bytes(pickle.dumps((inputs, step_s)))
    rows = tuple(args.gates.split(",")) if args.gates else (REFERENCE, *GATES)
    times: dict[str, list[float]] = {g: [] for g in rows}
    own: dict[str, list[float]] = {g: [] for g in rows}
    for _ in range(args.rounds):
        for g in rows:
            t, _, _, o = replay(dataclasses.replace(cfg, condition=g), g, inputs)
            times[g] += t
            own[g] += o
    memory = {g: replay(dataclasses.replace(cfg, condition=g), g, inputs, trace=True)[1:3]
              for g in rows}
    print(f"{cfg.scene.name}/{cfg.start}, {args.platform}, {args.steps} steps "
          f"({'degraded, drift' if args.degraded else 'nominal'}), {args.rounds} rounds; "
          f"mission median step {step_s:.3f} s")
    print(f"{'gate':12} {'median s':>9} {'max s':>8} {'% of step':>9} {'filter s':>9} "
          f"{'filter %':>9} {'held MB':>8} {'withheld':>9}")
    for g in rows:
        med, filt = statistics.median(times[g]), statistics.median(own[g])
        held, withheld = memory[g]
        print(f"{g:12} {med:9.4f} {max(times[g]):8.4f} {100 * med / step_s:9.1f} "
              f"{filt:9.4f} {100 * filt / step_s:9.1f} {held:8.1f} {withheld:9d}")
    if args.blocks:
        n = len(inputs)
        edges = [n * b // args.blocks for b in range(args.blocks + 1)]
        print("median s per block of steps (rounds pooled):")
        spans = zip(edges, edges[1:], strict=False)
        print(f"{'gate':12} " + " ".join(f"{f'{lo}-{hi - 1}':>9}" for lo, hi in spans)
              + f" {'last/first':>10}")
        for g in rows:
            per = [statistics.median(t for r in range(args.rounds)
                                     for t in times[g][r * n + lo:r * n + hi])
                   for lo, hi in zip(edges, edges[1:], strict=False)]
            print(f"{g:12} " + " ".join(f"{m:9.4f}" for m in per) + f" {per[-1] / per[0]:10.2f}")
    print("(median s: the gate module's whole step; filter s: the filter's own frame and test "
          f"within it; {REFERENCE}: the module with no filter)")


if __name__ == "__main__":
    main()
