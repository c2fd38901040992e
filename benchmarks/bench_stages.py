"""Benchmark: the planner's and the mapper's step on recorded inputs, in two trees, open loop.

A closed-loop mission's timings carry the noise of everything else the machine does, and a
small change to one stage drowns in it. This program records once what a study-like mission
gives its planner (everything ``BeamPlanner.plan`` is called with, at a few steps) and its
mapper (every sensor frame), then replays exactly those inputs in each tree, in fresh
processes, alternating between the trees round after round: the median time of
``BeamPlanner.plan`` per recorded step, and of each part of the mapper's step (the observed
surface, the occupancy grid, the model's window, the published prediction), with the ratio,
and whether both trees produced the same plans and the same mapper outputs to the bit. On a
shared machine, one round of one repeat swings by 1.5x even between identical trees: keep
the default rounds and repeats, or more.

Usage: .venv/bin/python benchmarks/bench_stages.py --baseline-tree PATH [--tree PATH]
           [--scene arch_field] [--condition gated] [--steps 80] [--rounds 3]
"""

from __future__ import annotations

import argparse
import hashlib
import inspect
import json
import os
import pickle
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
PARTS = ("surface", "grid", "model", "prediction")


def record(scene: str, start: str, condition: str, seed: int, steps: int, plan_steps: list[int],
           out: Path) -> None:
    """Run the mission as a study worker does and pickle its planner and mapper inputs."""
    import torch

    import mapper.mapper
    import planner.planner
    from mission.runtime.loop import run_in_process
    from mission.study.spec import RunSpec, StudyConfig, mission_config
    from rover_sim.catalog import resolve_scene
    from rovergate.runtime import tune_allocator

    tune_allocator()
    torch.set_num_threads(1)
    plans, frames = [], []
    plan, step = planner.planner.BeamPlanner.plan, mapper.mapper.Mapper.step

    def plan_recorded(self, t, *args, **kwargs):
        if t in plan_steps:  # pickled now: the planner's state (the flyer's free space) grows
            plans.append(pickle.dumps((t, args, kwargs)))
        return plan(self, t, *args, **kwargs)

    def step_recorded(self, frame):
        frames.append(frame)
        return step(self, frame)

    planner.planner.BeamPlanner.plan = plan_recorded
    mapper.mapper.Mapper.step = step_recorded
    with tempfile.TemporaryDirectory() as tmp:
        cfg = mission_config(StudyConfig(steps=steps), RunSpec(scene, start, condition, seed),
                             Path(tmp))
        resolve_scene(cfg.scene)
        run_in_process(cfg)
    out.write_bytes(pickle.dumps({"cfg": cfg, "plans": plans, "frames": frames}))


def replay(path: Path, repeats: int) -> dict:
    """Time the recorded steps in this process's tree; digests of what they produced."""
    import torch

    from mapper.integrate import backproject
    from mapper.mapper import Mapper
    from planner.planner import BeamPlanner
    from rovergate.runtime import tune_allocator

    tune_allocator()
    torch.set_num_threads(1)
    data = pickle.loads(path.read_bytes())
    out: dict = {"plan": {}, "parts": {p: [] for p in PARTS}}
    digest = hashlib.sha256()
    planner = BeamPlanner(data["cfg"])
    # A tree whose plan() takes fewer inputs than the recording tree's gets those it takes
    # (its plans then differ, and the digests say so).
    accepted = len(inspect.signature(planner.plan).parameters) - 1
    for blob in data["plans"]:
        times = []
        for _ in range(repeats):
            t, args, kwargs = pickle.loads(blob)  # afresh: plan() may change its inputs
            t0 = time.perf_counter()
            result = planner.plan(t, *args[:accepted], **kwargs)
            times.append(time.perf_counter() - t0)
        out["plan"][str(t)] = times
        for pose in result.path.poses:
            digest.update(pose.matrix().tobytes())
        digest.update(repr((result.gain, result.reason)).encode())
    mapper = Mapper.for_mission(data["cfg"])
    for frame in data["frames"]:
        T = frame.T_map_camera.matrix()
        tic = [time.perf_counter()]
        returns = backproject(frame.depth_m, frame.intrinsics, T)
        mapper.surface.integrate(returns)
        tic.append(time.perf_counter())
        if mapper.predictor is not None:
            mapper.grid.integrate(frame.depth_m, frame.intrinsics, T, returns_map=returns)
            tic.append(time.perf_counter())
            mapper.predictor.update(T[:3, 3])
            tic.append(time.perf_counter())
            points, prob = mapper.predictor.predicted()
            tic.append(time.perf_counter())
            digest.update(points.tobytes() + prob.tobytes() + mapper.grid.state.tobytes())
        digest.update(mapper.surface.points.tobytes() + mapper.surface.views.tobytes())
        for name, a, b in zip(PARTS, tic, tic[1:], strict=False):
            out["parts"][name].append(b - a)
    out["digest"] = digest.hexdigest()
    return out


def main(tree: Path, baseline_tree: Path, scene: str, start: str, condition: str, seed: int,
         steps: int, rounds: int, repeats: int) -> None:
    trees = {"after": tree.resolve(), "before": baseline_tree.resolve()}
    plan_steps = sorted({steps // 4, steps // 2, steps - 1})
    with tempfile.TemporaryDirectory(prefix="bench-stages-") as tmp:
        inputs = Path(tmp) / "inputs.pickle"
        print(f"recording {scene}/{start}, {condition}, seed {seed}, {steps} steps (planner "
              f"inputs at steps {plan_steps}) with {trees['after']}", flush=True)
        _child(trees["after"], ["--record", scene, start, condition, str(seed), str(steps),
                                ",".join(map(str, plan_steps)), str(inputs)])
        runs: dict[str, list[dict]] = {k: [] for k in trees}
        for r in range(rounds):
            for name in (list(trees) if r % 2 == 0 else list(trees)[::-1]):
                runs[name].append(json.loads(_child(trees[name], ["--replay", str(inputs),
                                                                 str(repeats)])))
            print(f"  round {r} done", flush=True)
    med = {k: {"plan": {t: statistics.median(x for run in v for x in run["plan"][t])
                        for t in v[0]["plan"]},
               "parts": {p: statistics.median(x for run in v for x in run["parts"][p])
                         for p in PARTS if v[0]["parts"][p]}}
           for k, v in runs.items()}
    print(f"\n{'median (ms)':<28}{'after':>10}{'before':>10}{'ratio':>8}")
    for t in med["after"]["plan"]:
        a, b = med["after"]["plan"][t], med["before"]["plan"][t]
        print(f"{'plan, step ' + t:<28}{1e3 * a:>10.2f}{1e3 * b:>10.2f}{b / a:>8.2f}")
    for p in med["after"]["parts"]:
        a, b = med["after"]["parts"][p], med["before"]["parts"][p]
        print(f"{'mapper: ' + p:<28}{1e3 * a:>10.2f}{1e3 * b:>10.2f}{b / a:>8.2f}")
    same = {run["digest"] for v in runs.values() for run in v}
    print(f"same plans and mapper outputs in both trees, every round: {len(same) == 1}")


def _child(tree: Path, args: list[str]) -> str:
    env = {**os.environ, "PYTHONPATH": str(tree), "OMP_NUM_THREADS": "1"}
    r = subprocess.run([sys.executable, __file__, *args], cwd=tree, env=env,
                       capture_output=True, text=True, timeout=3600)
    if r.returncode != 0:
        raise SystemExit(f"{args[0]} in {tree} failed:\n{r.stderr[-3000:]}")
    return r.stdout.strip().splitlines()[-1] if r.stdout.strip() else ""


def entrypoint() -> None:
    if len(sys.argv) > 1 and sys.argv[1] == "--record":
        scene, start, condition, seed, steps, plan_steps, out = sys.argv[2:9]
        record(scene, start, condition, int(seed), int(steps),
               [int(s) for s in plan_steps.split(",")], Path(out))
        return
    if len(sys.argv) > 1 and sys.argv[1] == "--replay":
        print(json.dumps(replay(Path(sys.argv[2]), int(sys.argv[3]))))
        return
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--baseline-tree", type=Path, required=True,
                    help="checkout of the code to compare with (e.g. the parent commit)")
    ap.add_argument("--tree", type=Path, default=REPO,
                    help="checkout of the code to measure (default: this one)")
    ap.add_argument("--scene", default="arch_field")
    ap.add_argument("--start", default="a")
    ap.add_argument("--condition", default="gated")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--steps", type=int, default=80, help="steps of the recorded mission")
    ap.add_argument("--rounds", type=int, default=3, help="replays per tree, alternating")
    ap.add_argument("--repeats", type=int, default=3, help="times each plan is timed per replay")
    a = ap.parse_args()
    main(a.tree, a.baseline_tree, a.scene, a.start, a.condition, a.seed, a.steps, a.rounds,
         a.repeats)


if __name__ == "__main__":
    entrypoint()
