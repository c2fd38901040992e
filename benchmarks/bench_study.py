"""Benchmark: a study's runs, timed as the study runs them, against an older tree if given one.

Runs short in-process missions exactly as a study worker does (``mission.study.runner``'s mission
config, the flyer, one torch thread, the tuned allocator), two at a time as the study's two
workers keep both cores busy, each in a fresh process. Prints, per condition, the median run
wall time, the median step and the median of every stage per step.

With ``--baseline-tree PATH`` (a checkout of the older code, e.g. ``git worktree add
/tmp/wt-base main``), the same missions also run with ``PYTHONPATH=PATH``: rounds alternate
between the trees (a pair of this tree's runs, then a pair of the other's), so that the load
of the machine falls on both alike, and the figures come with the ratio before / after and
whether each mission's coverage curve is identical in both trees. ``--tree PATH`` measures
another checkout than this one as "after" (one change at a time: a commit against its
parent). ``--save FILE`` writes the
figures as JSON; ``--baseline-json FILE`` compares with figures saved earlier instead (the
ratio then spans two runs of the benchmark: weaker than one run against a tree).

Usage: .venv/bin/python benchmarks/bench_study.py [--steps 40] [--seeds 0 1]
           [--conditions learned gated] [--scenes arch_field crater] [--baseline-tree PATH]
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

STAGES = ("render", "integrate", "gate", "plan", "execute")
REPO = Path(__file__).resolve().parents[1]


def run_one(scene: str, start: str, condition: str, seed: int, steps: int) -> dict:
    """One mission as a study worker runs it (mission/study/worker.py: ``init_worker`` and
    ``run_one``), in this process; its timings and coverage. Uses only what every tree
    compared has."""
    import torch

    from mission.runtime.loop import run_in_process
    from mission.study.spec import RunSpec, StudyConfig, mission_config
    from rover_sim.catalog import resolve_scene
    from rovergate.runtime import tune_allocator

    tune_allocator()
    torch.set_num_threads(1)
    with tempfile.TemporaryDirectory(prefix="bench-study-") as tmp:
        cfg = mission_config(StudyConfig(steps=steps), RunSpec(scene, start, condition, seed),
                             Path(tmp))
        resolve_scene(cfg.scene)
        record = run_in_process(cfg)
    return {"wall_s": record.wall_s, "step_s": record.step_wall_s,
            "stage_s": {s: record.stage_s.get(s, []) for s in STAGES},
            "coverage": record.coverage}


def _spawn(tree: Path, job: tuple, steps: int) -> dict:
    """Run one mission in a fresh process with ``PYTHONPATH=tree``."""
    scene, start, condition, seed = job
    env = {**os.environ, "PYTHONPATH": str(tree), "OMP_NUM_THREADS": "1"}
    r = subprocess.run([sys.executable, __file__, "--run-one", scene, start, condition,
                        str(seed), str(steps)], cwd=tree, env=env, capture_output=True,
                       text=True, timeout=1800)
    if r.returncode != 0:
        raise SystemExit(f"mission {job} in {tree} failed:\n{r.stderr[-3000:]}")
    return json.loads(r.stdout.strip().splitlines()[-1])


def figures(results: list[tuple[tuple, dict]]) -> dict:
    """Per condition: median run wall time, median step, median of each stage per step."""
    out = {}
    for condition in dict.fromkeys(job[2] for job, _ in results):
        runs = [r for job, r in results if job[2] == condition]
        out[condition] = {
            "runs": len(runs),
            "run_wall_s": statistics.median(r["wall_s"] for r in runs),
            "step_s": statistics.median(v for r in runs for v in r["step_s"]),
            "stage_s": {s: statistics.median(v for r in runs for v in r["stage_s"][s])
                        for s in STAGES if any(r["stage_s"][s] for r in runs)}}
    return out


def print_table(after: dict, before: dict | None, label: str) -> None:
    rows = [("run wall time (s)", "run_wall_s", None), ("whole step (s)", "step_s", None)]
    rows += [(f"  {s} (s/step)", "stage_s", s) for s in STAGES]
    for condition, a in after.items():
        b = before.get(condition) if before else None
        print(f"\n{condition} ({a['runs']} runs)")
        head = f"{'':<24}{'after':>10}"
        if b:
            head += f"{label:>10}{'ratio':>8}"
        print(head)
        for name, key, stage in rows:
            va = a[key] if stage is None else a[key].get(stage)
            if va is None:
                continue
            line = f"{name:<24}{va:>10.4f}"
            if b:
                vb = b[key] if stage is None else b[key].get(stage)
                if vb is not None:
                    line += f"{vb:>10.4f}{vb / va:>8.2f}"
            print(line)


def main(steps: int, seeds: list[int], conditions: list[str], scenes: list[str], start: str,
         rounds: int, tree: Path, baseline_tree: Path | None, baseline_json: Path | None,
         save: Path | None) -> None:
    jobs = [(scene, start, c, s) for scene in scenes for c in conditions for s in seeds]
    trees = {"after": tree.resolve()}
    if baseline_tree is not None:
        trees["before"] = baseline_tree.resolve()
    print(f"{len(jobs)} missions of {steps} steps ({', '.join(scenes)} / {start}; "
          f"{', '.join(conditions)}; seeds {', '.join(map(str, seeds))}) x {rounds} round(s), "
          f"two at a time, in {' and '.join(f'{k}={v}' for k, v in trees.items())}",
          flush=True)
    results: dict[str, list[tuple[tuple, dict]]] = {k: [] for k in trees}
    t0 = time.perf_counter()
    with ThreadPoolExecutor(2) as pool:
        for r in range(rounds):
            for i in range(0, len(jobs), 2):
                names = list(trees) if (r + i // 2) % 2 == 0 else list(trees)[::-1]
                for name in names:  # a pair of one tree's runs at once, then the other's
                    pair = jobs[i:i + 2]
                    done = list(pool.map(lambda j, n=name: _spawn(trees[n], j, steps), pair))
                    results[name] += list(zip(pair, done, strict=True))
                    print(f"  round {r} {name:>6}: " + ", ".join(
                        f"{j[0]}/{j[2]}/s{j[3]} {d['wall_s']:.1f} s" for j, d in zip(
                            pair, done, strict=True)), flush=True)
    after = figures(results["after"])
    before, label = None, "before"
    if "before" in results:
        before = figures(results["before"])
    elif baseline_json is not None:
        before, label = json.loads(baseline_json.read_text())["figures"], "saved"
    print_table(after, before, label)
    if "before" in results:
        same = [a[1]["coverage"] == b[1]["coverage"]
                for a, b in zip(results["after"], results["before"], strict=True)]
        print(f"\nidentical coverage curve in both trees: {sum(same)} of {len(same)} missions")
        wall = {k: sum(d["wall_s"] for _, d in v) for k, v in results.items()}
        print(f"all missions' wall time: before {wall['before']:.1f} s, after "
              f"{wall['after']:.1f} s, ratio {wall['before'] / wall['after']:.2f}")
    print(f"(benchmark took {time.perf_counter() - t0:.0f} s)")
    if save is not None:
        save.write_text(json.dumps({"steps": steps, "jobs": jobs, "figures": after},
                                   indent=1) + "\n")


def entrypoint() -> None:
    if len(sys.argv) > 1 and sys.argv[1] == "--run-one":  # a child: one mission, JSON out
        scene, start, condition, seed, steps = sys.argv[2:7]
        print(json.dumps(run_one(scene, start, condition, int(seed), int(steps))))
        return
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=40, help="planning steps per mission")
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    ap.add_argument("--conditions", nargs="+", default=["learned", "gated"])
    ap.add_argument("--scenes", nargs="+", default=["arch_field", "crater"])
    ap.add_argument("--start", default="a")
    ap.add_argument("--rounds", type=int, default=1, help="times every mission runs per tree")
    ap.add_argument("--tree", type=Path, default=REPO,
                    help="checkout of the code to measure (default: this one)")
    ap.add_argument("--baseline-tree", type=Path, help="checkout of the code to compare with")
    ap.add_argument("--baseline-json", type=Path, help="figures saved by --save, to compare")
    ap.add_argument("--save", type=Path, help="write this run's figures here (JSON)")
    a = ap.parse_args()
    main(a.steps, a.seeds, a.conditions, a.scenes, a.start, a.rounds, a.tree, a.baseline_tree,
         a.baseline_json, a.save)


if __name__ == "__main__":
    entrypoint()
