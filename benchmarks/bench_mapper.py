"""Benchmark: the mapper's cost per step with the learned occupancy, and its memory.

1. In one process, a rover mission on arch_field in the ``learned`` condition (30 steps): the
   median of the mapper's whole step (depth into S_t, depth into the occupancy grid, the
   model on the window, the prediction's points), and of each part, timed on the same frames.
   The same mission in ``obs`` (no model) gives the ratio.
2. The model's pass in each engine and precision (:mod:`mapper.engines`) on that mission's
   windows, taken in turn window by window: the median, its ratio to torch in float32 (the
   trained network as it runs in PyTorch), and how far its probabilities are from torch's
   float32 ones (largest difference, and 0.5 decisions flipped per covered voxel). An engine
   the CPU refuses (bfloat16 without native support) is named with the reason; one slower than
   a second a pass on the first window (torch's bfloat16 without it) is timed once on each of
   the next 7.
3. The occupancy grid's integration against OctoMap's (``octomap-python``, the OctoMap library
   the ROS ecosystem maps with, at the same 0.4 m voxel), on the same frames: returns per
   second and their ratio; OctoMap once on every return and once on the rays our grid carves
   (every second pixel of every second row).
4. The process set, ``learned``, 15 steps: the mapper process's median step and its peak
   resident memory (from its log).

One thread throughout, as a study worker runs (OpenMP too, which OctoMap uses). Run it as
well under ``ONEDNN_MAX_CPU_ISA=AVX2 ATEN_CPU_CAPABILITY=avx2``, oneDNN's and ATen's caps,
for a CPU without AVX-512.

Usage: .venv/bin/python benchmarks/bench_mapper.py [--steps 30] [--repeats 3]
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import re
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")  # before any library starts its OpenMP pool

import numpy as np  # noqa: E402
import torch  # noqa: E402

from mapper.engines import ENGINES, PRECISIONS, make_engine  # noqa: E402
from mapper.grid import GridSpec, OccupancyGrid  # noqa: E402
from mapper.integrate import backproject  # noqa: E402
from mapper.mapper import Mapper  # noqa: E402
from mapper.model import crop  # noqa: E402
from mission.runtime.loop import run_in_process  # noqa: E402
from rover_sim.catalog import resolve_scene  # noqa: E402
from rover_sim.sim import RoverSim  # noqa: E402
from rovergate.config import MissionConfig  # noqa: E402
from rovergate.runtime import tune_allocator  # noqa: E402


def mission(condition: str, steps: int, out: Path) -> MissionConfig:
    cfg = MissionConfig(condition=condition, steps=steps, in_process=True, progress=False)
    cfg.out = str(out)
    resolve_scene(cfg.scene)
    return cfg


def parts(cfg: MissionConfig, poses: list, frames: list, windows: list
          ) -> dict[str, list[float]]:
    """Times of each part of the mapper's step, over the frames of ``poses``; appends each
    frame (depth, intrinsics, camera pose, returns) to ``frames`` and each state window the
    model ran on to ``windows``."""
    sim = RoverSim(cfg)
    mapper = Mapper.for_mission(cfg)
    times: dict[str, list[float]] = {"surface": [], "grid": [], "model": [], "points": []}
    try:
        for t, state in enumerate(poses):
            sim.state = state
            f = sim.render(t)
            T = f.T_map_camera.matrix()
            t0 = time.perf_counter()
            returns = backproject(f.depth_m, f.intrinsics, T)
            mapper.surface.integrate(returns)
            t1 = time.perf_counter()
            mapper.grid.integrate(f.depth_m, f.intrinsics, T, returns_map=returns)
            t2 = time.perf_counter()
            frames.append((f.depth_m, f.intrinsics, T, returns))
            w = mapper.predictor.window
            windows.append(crop(mapper.grid.state, w.start(mapper.grid.spec, T[:3, 3]), w.size))
            mapper.predictor.update(T[:3, 3])
            t3 = time.perf_counter()
            mapper.predictor.predicted()
            t4 = time.perf_counter()
            for k, v in zip(times, (t1 - t0, t2 - t1, t3 - t2, t4 - t3), strict=True):
                times[k].append(v)
    finally:
        sim.close()
    return times


SLOW_S = 1.0  # an engine slower than this a pass is timed on fewer windows
SLOW_WINDOWS = 8


def engines(windows: list[np.ndarray], repeats: int) -> None:
    """The model's pass in every engine and precision on the same windows, in turn."""
    from mapper.model import load_checkpoint
    from mapper.predictor import to_float16
    ckpt = load_checkpoint()
    runs, refused = {}, {}
    for name in ENGINES:
        for precision in PRECISIONS:
            try:
                runs[name, precision] = make_engine(ckpt, name, precision)
            except Exception as e:  # refused here (bfloat16 without native support)
                refused[name, precision] = str(e)
    times = {k: [] for k in runs}
    worst = {k: 0.0 for k in runs}
    flips = {k: 0 for k in runs}
    seen = {k: 0 for k in runs}  # windows each engine ran on
    slow = set()  # over SLOW_S a pass: once a window, on the first SLOW_WINDOWS windows
    unique = [w for i, w in enumerate(windows) if i == 0 or not np.array_equal(w, windows[i - 1])]
    for i, state in enumerate(unique):
        probs = {}
        for key, engine in runs.items():
            if key in slow and i >= SLOW_WINDOWS:
                continue
            for _ in range(1 if key in slow else repeats):
                t0 = time.perf_counter()
                logits = engine(state)
                times[key].append(time.perf_counter() - t0)
            if i == 0 and min(times[key]) > SLOW_S and key != ("torch", "float32"):
                slow.add(key)  # judged on the first window's fastest pass, past any warm-up
            seen[key] += 1
            probs[key] = to_float16(1.0 / (1.0 + np.exp(-logits.astype(np.float64)))
                                    ).astype(np.float32)
        ref = probs["torch", "float32"]
        for key, p in probs.items():
            worst[key] = max(worst[key], float(np.abs(p - ref).max()))
            flips[key] += int(np.count_nonzero((p >= 0.5) != (ref >= 0.5)))
    base = statistics.median(times["torch", "float32"])
    print(f"\nthe model's pass on {len(unique)} windows of that mission, {repeats} times each, "
          f"one thread; CPU capability {torch.backends.cpu.get_cpu_capability()}")
    print(f"{'engine':<10}{'precision':<11}{'median ms':>10}{'vs torch float32':>18}"
          f"{'max |dp|':>10}{'flips per voxel':>17}")
    for (name, precision), t in times.items():
        med_t = statistics.median(t)
        note = (f"  (over {SLOW_S:.0f} s a pass: {repeats} passes on the first window, then one"
                f" on each of the next {seen[name, precision] - 1})"
                if (name, precision) in slow else "")
        print(f"{name:<10}{precision:<11}{1000 * med_t:>10.1f}{base / med_t:>17.2f}x"
              f"{worst[name, precision]:>10.4f}"
              f"{flips[name, precision] / (seen[name, precision] * unique[0].size):>17.1e}{note}")
    for (name, precision), why in refused.items():
        print(f"{name:<10}{precision:<11}refused: {why}")


def octomap_ratio(cfg: MissionConfig, frames: list, repeats: int) -> None:
    """Our grid's integration of each frame against OctoMap's, returns per second."""
    try:
        import octomap
    except ImportError:
        print("\nOctoMap comparison skipped: pip install octomap-python")
        return
    from mapper.model import load_checkpoint
    spec = GridSpec.around(cfg.scene.bounds_m, load_checkpoint().window.voxel_m)
    ours, full, same = [], [], []
    stride = OccupancyGrid(spec).ray_stride_px
    grid, tree, tree_same = (OccupancyGrid(spec), octomap.OcTree(spec.voxel_m),
                             octomap.OcTree(spec.voxel_m))
    returns_total = 0
    for depth, k, T, returns in frames:
        sub = np.full_like(depth, np.nan)
        sub[::stride, ::stride] = depth[::stride, ::stride]
        carved = backproject(sub, k, T).astype(np.float64)
        pts = returns.astype(np.float64)
        origin = T[:3, 3].astype(np.float64)
        returns_total += len(pts)
        for _ in range(repeats):  # each time the same rays, so the same work
            t0 = time.perf_counter()
            grid.integrate(depth, k, T, returns_map=returns)
            t1 = time.perf_counter()
            tree.insertPointCloud(pts, origin, maxrange=cfg.sensor.max_range_m)
            t2 = time.perf_counter()
            tree_same.insertPointCloud(carved, origin, maxrange=cfg.sensor.max_range_m)
            t3 = time.perf_counter()
            ours.append(len(pts) / (t1 - t0))
            full.append(len(pts) / (t2 - t1))
            same.append(len(pts) / (t3 - t2))
    print(f"\nintegration of {len(frames)} frames ({returns_total / len(frames):.0f} returns a "
          f"frame, {spec.voxel_m} m voxels), median returns per second, one thread:")
    m_ours = statistics.median(ours)
    for label, v in (("our grid (occupied, free along every 4th ray)", ours),
                     ("OctoMap, every return's ray", full),
                     ("OctoMap, only the rays our grid carves", same)):
        print(f"  {label:<48}{statistics.median(v):>12,.0f}  ours / it "
              f"{m_ours / statistics.median(v):5.1f}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=30)
    ap.add_argument("--repeats", type=int, default=3, help="timings of each window or frame")
    args = ap.parse_args()
    torch.set_num_threads(1)
    tune_allocator()  # as every rovergate program does (rovergate/runtime.py)
    logging.basicConfig(level=logging.WARNING)
    print(f"torch {torch.__version__}, {torch.get_num_threads()} threads")
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        med = {}
        for condition in ("obs", "learned"):
            rec = run_in_process(mission(condition, args.steps, tmp / condition))
            med[condition] = statistics.median(rec.stage_s["integrate"])
            print(f"in process, {condition:8s}: mapper step median {1000 * med[condition]:6.1f} ms"
                  f" over {args.steps + 1} frames (max "
                  f"{1000 * max(rec.stage_s['integrate']):.0f} ms)")
            if condition == "learned":
                poses = [(x, y, 0.0) for x, y in rec.base_xy]
                yaws = [float(np.arctan2(b[1] - a[1], b[0] - a[0]))
                        for a, b in zip(rec.base_xy, rec.base_xy[1:], strict=False)]
                poses = [(x, y, yw) for (x, y, _), yw in zip(poses, [0.0, *yaws], strict=True)]
                frames, windows = [], []
                cfg = mission(condition, args.steps, tmp / "parts")
                split = parts(cfg, poses, frames, windows)
                print("  parts (median ms): " + ", ".join(
                    f"{k} {1000 * statistics.median(v):.1f}" for k, v in split.items()))
        print(f"ratio learned / obs: {med['learned'] / med['obs']:.1f}")
        engines(windows, args.repeats)
        octomap_ratio(cfg, frames, args.repeats)
        out = tmp / "procs"
        r = subprocess.run([sys.executable, "-m", "mission.cli", "run", "--condition",
                            "learned", "--steps", "15", "--no-progress", "--out", str(out)],
                           capture_output=True, text=True, timeout=600)
        if r.returncode != 0:
            raise SystemExit(f"process-set mission failed:\n{r.stderr[-2000:]}")
        metrics = json.loads((out / "metrics.json").read_text())
        log = (out / "logs" / "mapper.log").read_text()
        peak = re.findall(r"peak resident memory (\d+) MB", log)
        print(f"process set, learned : mapper step median "
              f"{1000 * metrics['median_stage_s']['integrate']:.1f} ms; mapper process peak "
              f"resident memory {peak[-1] if peak else '?'} MB")


if __name__ == "__main__":
    main()
