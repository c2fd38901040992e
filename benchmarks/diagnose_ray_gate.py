"""Diagnosis: why the ray-consistent gate withholds what it does, and not what the frustum
gate withholds.

Runs one in-process mission under `learned` (nothing withheld changes the path), records the
gate's inputs, then at the last step takes the predicted points the frustum gate (`gated`)
withholds and, for every frame whose frustum held one of them, reads the return at its pixel:
nearer than the point by more than the tolerance (hidden), within the ray gate's margin of it
(on a surface), at least the margin beyond it (the ray passed through it: the ray gate's
evidence), no return within range (+Inf), no return at all (dropped), or a return the ray
gate's grazing rule rejects. Prints the shares of those frame-point pairs, split by whether
the point is an oracle false positive (farther than 0.03 d_scene from the true surface).

Usage: .venv/bin/python benchmarks/diagnose_ray_gate.py [--platform flyer] [--scene arch_field]
           [--steps 30] [--degraded]
"""

from __future__ import annotations

import argparse
import logging
import tempfile
from pathlib import Path

import numpy as np
from bench_gates import record  # the same directory

from gate.filter import ObservationGate, RayGate
from gate.views import pixels
from mission.scoring.evaluation import StepEvaluator
from rover_sim.catalog import load_scene, resolve_scene
from rovergate.config import MissionConfig, SensingConfig
from rovergate.geometry import in_region
from rovergate.types import xyz


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--platform", default="flyer")
    ap.add_argument("--scene", default="arch_field")
    ap.add_argument("--steps", type=int, default=30)
    ap.add_argument("--degraded", action="store_true",
                    help="blob dropout 0.1, noise 1%%, grazing 80 deg")
    args = ap.parse_args()
    logging.basicConfig(level=logging.WARNING)
    sensing = (SensingConfig(noise_frac=0.01, dropout_blob_frac=0.1, grazing_max_deg=80.0)
               if args.degraded else SensingConfig())
    cfg = MissionConfig(steps=args.steps, condition="learned", platform=args.platform,
                        sensing=sensing, progress=False,
                        out=Path(tempfile.mkdtemp(prefix="rovergate-diagnose-")))
    cfg.scene.name = args.scene
    resolve_scene(cfg.scene)
    inputs, _ = record(cfg)
    g, s = cfg.gate, cfg.sensor
    eps = g.epsilon_m(cfg.scene.d_scene_m)
    frustum = ObservationGate(g.k, eps, s.min_range_m, s.max_range_m)
    ray = RayGate(g.k, eps, s.min_range_m, s.max_range_m, g.ray_margin_m, g.ray_grazing_max_deg)
    for _, pose, info, depth, cov in inputs:
        T = pose.matrix()
        frustum.add_frame(T, info, depth, cov)
        ray.add_frame(T, info, depth, cov)
    mapped = inputs[-1][0]
    pred = xyz(mapped.predicted)
    pred = pred[in_region(pred, cfg.scene.bounds_m)]
    withheld = pred[frustum.unsupported(pred, xyz(mapped.surface))]
    # The evaluation's reference O*, as the mission builds it (evaluation only).
    judge = StepEvaluator(cfg, load_scene(cfg.scene).surface_samples(cfg.eval.n_samples,
                                                                    seed=0))
    d, _ = judge.tree.query(withheld)
    fp = d > cfg.oracle_delta_m
    kinds = ("hidden", "on a surface", "passed through", "+Inf", "dropped", "grazing")
    counts = {k: np.zeros(len(kinds), dtype=np.int64)
              for k in ("false positive", "true surface")}
    for (R, t, k, usable), (_, _, _, depth, _) in zip(ray._frames, inputs, strict=True):
        idx, v, u, z = pixels(withheld.astype(np.float64), R, t, k, s.min_range_m,
                              s.max_range_m)
        raw, d = np.asarray(depth)[v, u], usable[v, u]
        with np.errstate(invalid="ignore"):
            kind = np.select([np.isposinf(raw), np.isnan(raw), np.isnan(d),
                              d < z - g.view_tolerance_m, d < z + g.ray_margin_m],
                             [3, 4, 5, 0, 1], default=2)
        for name, mask in (("false positive", fp[idx]), ("true surface", ~fp[idx])):
            counts[name] += np.bincount(kind[mask], minlength=len(kinds))
    print(f"{args.scene}/a, {args.platform}, {args.steps} steps"
          f"{', degraded' if args.degraded else ''}: the frustum gate withholds {len(withheld)} "
          f"predicted points at the last step ({int(fp.sum())} oracle false positives)")
    print(f"{'':16}" + "".join(f"{k:>15}" for k in kinds) + f"{'frame-points':>14}")
    for name, c in counts.items():
        total = max(int(c.sum()), 1)
        print(f"{name:16}" + "".join(f"{100 * x / total:14.1f}%" for x in c) + f"{total:14d}")


if __name__ == "__main__":
    main()
