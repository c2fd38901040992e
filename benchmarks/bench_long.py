"""Benchmark: the soak. A long rover mission over ground it keeps finding, per 100-step block.

Runs a ``--steps`` (2,000) rover mission on ``long_traverse`` (a 240 m plain, 600 rocks;
``obs`` by default, ``--condition``), with the suite's absolute tolerances (tau 0.21 m,
epsilon and delta 1.28 m: the scene's d_scene is 340 m, so the fractions are set from those)
and ``--planner.explore-below 50`` (``--explore-below``: a rover whose surroundings are all
seen heads away from where it has been; without it, it dithers once they are, and the soak
would measure a rover standing still), twice:

- **in process**, in a child of this program (``run_in_process``): each step's end time, the
  process's resident memory and the bag's size, as the step ends;
- **as the process set**, with the ground link's default contact plan (a window every 25
  steps) and a ground station connected (``rovergate ground --mission OUT``), and a Zenoh
  client on the mission's ``--listen`` endpoint that counts the bytes of every sample under
  ``rover/**`` (what a remote subscriber receives) and the steps of the clock's ticks; at
  each tick, the resident memory of the mission manager and of every process under it, and
  the sizes of the bag, ``checkpoint.sqlite`` and ``journal.sqlite``. At ``--kill-at``
  (1,500) the mission manager is SIGKILLed; ``rovergate run --out OUT --resume`` carries on,
  timed to its "resumed at step" line, and a new station connects.

Prints per block: the median step time, the true surface newly covered per step (samples of
the evaluator's 100,000; where the rover still explores), each process's resident memory at
the block's end, and bytes per step on the wire, in the bag and in the checkpoint; then each
column's slope per 1,000 steps, the ratio of the last block's median step to that of steps
100-200 (issue 30's target: at most 1.2), the resume time (target: under 10 s) and whether
the process set's per-step coverage equals the in-process run's (it must, to the bit).

Usage: .venv/bin/python benchmarks/bench_long.py [--steps 2000] [--kill-at 1500]
           [--block 100] [--condition obs] [--modes in-process,processes] [--out DIR]
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import statistics
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
SCENE = "long_traverse"
TAU_M, EPSILON_M = 0.21, 1.28  # arch_field's, in metres (0.005 and 0.03 of its d_scene)
MODULES = ("sim", "mapper", "gate", "planner")


def mission_flags(args: argparse.Namespace, d_scene_m: float) -> list[str]:
    eps = f"{EPSILON_M / d_scene_m:.6g}"
    return ["--scene.name", SCENE, "--start", "a", "--steps", str(args.steps),
            "--condition", args.condition, "--eval.tau-frac", f"{TAU_M / d_scene_m:.6g}",
            "--gate.epsilon-frac", eps, "--gate.oracle-delta-frac", eps, "--no-progress",
            "--planner.explore-below", str(args.explore_below)]


def rss_mb(pid: int) -> float | None:
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    except (FileNotFoundError, ProcessLookupError):
        return None
    return None


def descendants(pid: int) -> dict[str, int]:
    """The live processes under ``pid``, by name (a module's ``rovergate NAME``, else the
    program's name)."""
    children: dict[int, list[int]] = {}
    for d in Path("/proc").iterdir():
        if d.name.isdigit():
            try:
                ppid = int((d / "stat").read_text().rsplit(")", 1)[1].split()[1])
            except (FileNotFoundError, ProcessLookupError, IndexError):
                continue
            children.setdefault(ppid, []).append(int(d.name))
    out: dict[str, int] = {}
    todo = list(children.get(pid, []))
    while todo:
        p = todo.pop()
        todo += children.get(p, [])
        try:
            argv = Path(f"/proc/{p}/cmdline").read_bytes().split(b"\0")
        except (FileNotFoundError, ProcessLookupError):
            continue
        # A forked module names itself "rovergate NAME ..." (one string, its process title).
        words = " ".join(w.decode(errors="replace") for w in argv if w).split()
        if len(words) > 1 and Path(words[0]).name == "rovergate":
            name = words[1]
        elif len(words) > 1 and words[1].endswith("bench_long.py"):
            name = "bench"
        elif words:
            name = Path(words[0]).name + (f" {words[2]}" if words[1:2] == ["-m"] else "")
        else:
            name = str(p)
        out[name if name not in out else f"{name}-{p}"] = p
    return out


def size(*paths: Path) -> int:
    total = 0
    for p in paths:
        if p.is_dir():
            total += sum(f.stat().st_size for f in p.iterdir() if f.is_file())
        else:
            for f in (p, p.with_name(p.name + "-wal")):
                if f.exists():
                    total += f.stat().st_size
    return total


# --- in process ---------------------------------------------------------------------------------

def child_in_process(out: Path, flags: list[str]) -> None:
    """The in-process mission, in this (child) process: one JSON line per step."""
    import tyro

    from mission.run import check_runnable
    from mission.runtime.loop import run_in_process
    from mission.scoring.report import write_report
    from rovergate.config import MissionConfig
    from rovergate.runtime import tune_allocator
    tune_allocator()
    cfg = tyro.cli(MissionConfig, args=[*flags, "--in-process", "--out", str(out)])
    check_runnable(cfg)  # (resolves the scene)
    log = (out / "steps.jsonl").open("w")
    from mapper.mapper import Mapper
    surface = {"points": 0}  # the size of S_t after each step (the map memory grows with)
    mapper_step = Mapper.step

    def counted_step(self, frame):
        result = mapper_step(self, frame)
        surface["points"] = len(self.surface)
        return result
    Mapper.step = counted_step  # type: ignore[method-assign]

    def on_step(t: int, coverage: float) -> None:
        log.write(json.dumps({"step": t, "t": time.perf_counter(), "coverage": coverage,
                              "surface": surface["points"],
                              "rss": {"in-process": rss_mb(os.getpid()),
                                      **{n: rss_mb(p) for n, p in
                                         descendants(os.getpid()).items()}},
                              "bag": size(*out.glob("bag*"))}) + "\n")
        log.flush()
    record = run_in_process(cfg, on_step)
    write_report(cfg, record, out)
    log.close()
    (out / "stages.json").write_text(json.dumps(record.stage_s))


def run_in_process_child(out: Path, flags: list[str]) -> list[dict]:
    out.mkdir(parents=True, exist_ok=True)
    r = subprocess.run([sys.executable, __file__, "--child-in-process", str(out), "--",
                        *flags], capture_output=True, text=True, timeout=6 * 3600)
    if r.returncode != 0:
        raise SystemExit(f"the in-process mission failed:\n{r.stderr[-3000:]}")
    return [json.loads(line) for line in (out / "steps.jsonl").read_text().splitlines()]


# --- the process set ----------------------------------------------------------------------------

class Tap:
    """A Zenoh client on the mission's endpoint: bytes of every sample under ``rover/**``,
    and at each tick of the clock the step's row (time, memory, file sizes)."""

    def __init__(self, port: int, sample) -> None:
        import zenoh

        from rovergate.messages import decode
        from rovergate.session import SessionConfig, zenoh_config
        self.rows: list[dict] = []
        self.bytes = 0
        self.cv = threading.Condition()
        self.session = zenoh.open(zenoh_config(SessionConfig(
            mode="client", connect=(f"tcp/127.0.0.1:{port}",))))

        def on_sample(s) -> None:
            n = len(s.payload)
            with self.cv:
                self.bytes += n
                if str(s.key_expr) == "rover/mission/status":
                    step, _ = decode("status", s.payload.to_bytes())
                    if not self.rows or step > self.rows[-1]["step"]:
                        self.rows.append({"step": step, "t": time.perf_counter(),
                                          "wire": self.bytes, **sample()})
                    self.cv.notify_all()
        self._sub = self.session.declare_subscriber("rover/**", on_sample)

    def wait_step(self, step: int, timeout_s: float) -> None:
        with self.cv:
            if not self.cv.wait_for(lambda: self.rows and self.rows[-1]["step"] >= step,
                                    timeout_s):
                raise SystemExit(f"no tick of step {step} within {timeout_s:.0f} s")

    def close(self) -> None:
        self._sub.undeclare()
        self.session.close()


def run_process_set(out: Path, flags: list[str], kill_at: int, steps: int
                    ) -> tuple[list[dict], dict]:
    sys.path.insert(0, str(ROOT / "tests"))
    from conftest import RovergateProcess, wait_gone

    from rovergate.session import free_loopback_port
    port = free_loopback_port()
    ground_out = out.with_name(out.name + "-ground")
    manager: dict = {}

    def sample() -> dict:
        pid = manager["pid"]
        return {"rss": {"manager": rss_mb(pid),
                        **{n: rss_mb(p) for n, p in descendants(pid).items()}},
                "bag": size(*out.glob("bag*")), "checkpoint": size(out / "checkpoint.sqlite"),
                "journal": size(out / "journal.sqlite")}

    def station() -> RovergateProcess:
        return RovergateProcess(["ground", "--mission", str(out), "--out", str(ground_out),
                                 "--no-stdin"])

    first = RovergateProcess(["run", *flags, "--out", str(out),
                              "--listen", f"tcp/127.0.0.1:{port}"])
    manager["pid"] = first.proc.pid
    first.wait_for_line("link to the ground on", 300)
    ground = station()
    tap = Tap(port, sample)
    info: dict = {}
    try:
        if kill_at and kill_at < steps:
            tap.wait_step(kill_at, 6 * 3600)
            pids = [first.pid(m) for m in MODULES]
            os.kill(first.proc.pid, signal.SIGKILL)
            first.finish(60)
            for pid in pids:
                wait_gone(pid, 60)
            ground.finish(120)
            t0 = time.perf_counter()
            resumed = RovergateProcess(["run", "--out", str(out), "--resume", "--no-progress"])
            manager["pid"] = resumed.proc.pid
            m = resumed.wait_for_line(r"resumed at step (\d+)", 600)
            info["resume_s"] = time.perf_counter() - t0
            info["resumed_at"] = int(m.group(1))
            info["killed_after"] = tap.rows[-1]["step"]
            resumed.wait_for_line("link to the ground on", 300)
            ground = station()
            first = resumed
        code = first.finish(6 * 3600)
        if code != 0:
            raise SystemExit(f"the process-set mission failed:\n{first.text[-3000:]}")
        ground.finish(600)
    finally:
        tap.close()
        for p in (first, ground):
            p.kill()
    return tap.rows, info


# --- the report ---------------------------------------------------------------------------------

def slope_per_1000(x: list[float], y: list[float]) -> float:
    ok = [(a, b) for a, b in zip(x, y, strict=True) if b is not None and np.isfinite(b)]
    if len(ok) < 2:
        return float("nan")
    a, b = np.array(ok).T
    return float(np.polyfit(a, b, 1)[0] * 1000)


def report(name: str, rows: list[dict], coverage: list[float], n_truth: int, block: int,
           kill: int | None = None) -> dict:
    """Print the mode's table; returns the figures the summary needs."""
    by_step = {r["step"]: r for r in rows}
    steps = sorted(by_step)
    dt = {s: by_step[s]["t"] - by_step[s - 1]["t"] for s in steps if s - 1 in by_step
          and not (kill is not None and s - 1 <= kill < s + 1)}
    procs = sorted({n for r in rows for n in r["rss"] if n.split("-")[0] != "python3"})
    mapped = any("surface" in r for r in rows)
    cols = ["steps", "median s", "new/step"] + (["S_t points"] if mapped else []) + \
        [f"{p} MB" for p in procs] + ["wire kB/st", "bag kB/st", "ckpt B/st"]
    print(f"\n{name}: per {block}-step block (new/step: true-surface samples of {n_truth:,} "
          "newly covered per step; memory at the block's end)")
    print(" | ".join(cols))
    mids, table = [], []
    last = steps[-1]
    for lo in range(1, last, block):
        hi = min(lo + block, last + 1)
        times = [dt[s] for s in range(lo, hi) if s in dt]
        if not times or hi - 1 not in by_step or lo - 1 not in by_step:
            continue
        a, b = by_step[lo - 1], by_step[hi - 1]
        n = hi - lo
        new = (coverage[hi - 1] - coverage[lo - 1]) * n_truth / n \
            if hi - 1 < len(coverage) else float("nan")

        def per_step(key: str, a=a, b=b, n=n) -> float | None:
            if key not in a or key not in b:
                return None
            return (b[key] - a[key]) / n
        row = {"median": statistics.median(times), "new": new,
               **{p: b["rss"].get(p) for p in procs},
               "wire": per_step("wire"), "bag": per_step("bag"),
               "checkpoint": per_step("checkpoint")}
        mids.append((lo + hi - 1) / 2)
        table.append(row)

        def fmt(v, scale=1.0, digits=1):
            return "-" if v is None else f"{v / scale:.{digits}f}"
        row["surface"] = b.get("surface")
        print(" | ".join([f"{lo - 1}-{hi - 1}", f"{row['median']:.3f}", f"{new:.0f}",
                          *([f"{b['surface']:,}"] if mapped else []),
                          *[fmt(row[p], 1, 0) for p in procs], fmt(row["wire"], 1e3),
                          fmt(row["bag"], 1e3), fmt(row["checkpoint"], 1, 0)]))
    slopes = {k: slope_per_1000(mids, [r[k] for r in table])
              for k in ["median", "new", *procs, "wire", "bag", "checkpoint"]}
    print("slope per 1,000 steps: " + ", ".join(
        f"{k} {v:+.3g}" + (" s" if k == "median" else " MB" if k in procs else
                          " B/step" if k in ("wire", "bag", "checkpoint") else "")
        for k, v in slopes.items() if np.isfinite(v)))
    if mapped and len(table) > 2:  # memory against the map: MB per million points of S_t
        for p in procs:
            pts = [r["surface"] for r in table if r.get(p) is not None]
            mem = [r[p] for r in table if r.get(p) is not None]
            if len(pts) > 2 and pts[-1] > pts[0]:
                fit = np.polyfit(np.array(pts) / 1e6, mem, 1)
                resid = np.array(mem) - np.polyval(fit, np.array(pts) / 1e6)
                print(f"{p}: {fit[0]:.0f} MB per million points of S_t (+{fit[1]:.0f} MB; "
                      f"residual within {np.abs(resid).max():.0f} MB)")
    # The comparison: the last block against the second (steps 100-200 of 2,000).
    early = [dt[s] for s in range(block + 1, 2 * block + 1) if s in dt]
    late = [dt[s] for s in range(last - block + 1, last + 1) if s in dt]
    out: dict = {"slopes": slopes, "blocks": table, "mids": mids}
    if early and late and len(coverage) > last:
        out.update(early_s=statistics.median(early), late_s=statistics.median(late),
                   new_early=(coverage[2 * block] - coverage[block]) * n_truth / block,
                   new_late=(coverage[last] - coverage[last - block]) * n_truth / block)
        out["ratio"] = out["late_s"] / out["early_s"]
        print(f"median step, steps {last - block}-{last} over steps {block}-{2 * block}: "
              f"{out['ratio']:.2f} ({out['late_s']:.3f} s / {out['early_s']:.3f} s); newly "
              f"covered per step {out['new_late']:.0f} against {out['new_early']:.0f}")
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=2000)
    ap.add_argument("--kill-at", type=int, default=1500,
                    help="SIGKILL the process set's mission manager at this step (0: never)")
    ap.add_argument("--block", type=int, default=100)
    ap.add_argument("--condition", default="obs")
    ap.add_argument("--explore-below", type=int, default=50,
                    help="--planner.explore-below: where nothing is left to see within reach, "
                         "the rover heads away from where it has been (0: off)")
    ap.add_argument("--modes", default="in-process,processes")
    ap.add_argument("--out", type=Path, default=None,
                    help="where the missions go (default: a new temporary directory)")
    ap.add_argument("--child-in-process", type=Path, help=argparse.SUPPRESS)
    args, rest = ap.parse_known_args()
    if args.child_in_process:
        child_in_process(args.child_in_process, [a for a in rest if a != "--"])
        return
    from rover_sim.catalog import load_scene
    from rovergate.runtime import tune_allocator
    tune_allocator()
    scene = load_scene(SCENE)
    flags = mission_flags(args, scene.d_scene_m)
    base = args.out or Path(__import__("tempfile").mkdtemp(prefix="rovergate-bench-long-"))
    base.mkdir(parents=True, exist_ok=True)
    modes = args.modes.split(",")
    print(f"{args.steps}-step rover mission on {SCENE}/a ({args.condition}), in {base}; "
          f"CPU: {os.cpu_count()} cores")
    results, coverage = {}, {}
    for mode in modes:
        out = base / mode
        t0 = time.perf_counter()
        if mode == "in-process":
            rows, info = run_in_process_child(out, flags), {}
        elif mode == "processes":
            rows, info = run_process_set(out, flags, args.kill_at, args.steps)
        else:
            raise SystemExit(f"--modes: unknown mode {mode!r} (in-process, processes)")
        metrics = json.loads((out / "metrics.json").read_text())
        coverage[mode] = metrics["coverage"]
        n_truth = int(metrics.get("truth_samples", 0)) or len(scene.surface_samples(100_000))
        print(f"\n{mode}: {time.perf_counter() - t0:.0f} s in all; final coverage "
              f"{metrics['final_coverage']:.4f}, {metrics['collisions']} collisions, "
              f"{metrics['stuck_steps']} stuck steps, {metrics['path_length_m']:.0f} m driven")
        results[mode] = report(mode, rows, coverage[mode], n_truth, args.block,
                               info.get("killed_after"))
        if info:
            print(f"mission manager SIGKILLed after the tick of step {info['killed_after']}: "
                  f"`--resume` ran the loop again at step {info['resumed_at']} "
                  f"{info['resume_s']:.1f} s after it started (target: under 10 s)")
        stages = out / "stages.json"
        if stages.exists():  # in process: where a step's time went, block by block
            per = json.loads(stages.read_text())
            print("median s per stage: " + "; ".join(
                f"{name} " + " ".join(f"{statistics.median(v[lo:lo + args.block]):.3f}"
                                      for lo in range(0, len(v), args.block * 4))
                for name, v in sorted(per.items()) if v)
                  + f" (every {args.block * 4} steps)")
    if len(coverage) == 2:
        same = coverage["in-process"] == coverage["processes"]
        print(f"\nper-step coverage, process set (killed and resumed) against in process: "
              f"{'identical' if same else 'DIFFERENT'}")
    (base / "summary.json").write_text(json.dumps(results, indent=1, default=float))


if __name__ == "__main__":
    main()
