"""Benchmark: render-and-publish rate per platform and scene, and coverage-update time.

For every scene and both platforms, renders frames around the start (the camera turning 18
degrees a frame), applies the sensing model, encodes the depth, camera info and poses as CDR
and puts them on a Zenoh session (loopback, no subscriber), and reports frames per second
(median over frames). Then it integrates those frames into S_t with the mapper and times each
step's coverage update against ~100k ground-truth samples. Everything is measured in one run.

Usage: .venv/bin/python benchmarks/bench_world.py [--frames 20] [--scenes a b ...] [--degraded]
"""

from __future__ import annotations

import argparse
import logging
import statistics
import time

import numpy as np
import zenoh

from mapper.mapper import Mapper
from mission.scoring.coverage import CoverageEvaluator
from rover_sim.catalog import SCENES, resolve_scene
from rover_sim.sim import RoverSim
from rovergate.config import MissionConfig, SceneConfig, SensingConfig
from rovergate.keys import Keys
from rovergate.messages import encode
from rovergate.runtime import tune_allocator
from rovergate.session import SessionConfig, zenoh_config
from rovergate.types import xyz


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=20)
    ap.add_argument("--scenes", nargs="*", default=list(SCENES))
    ap.add_argument("--degraded", action="store_true",
                    help="noise, blob and pixel dropout, grazing dropout and drift all on")
    args = ap.parse_args()
    tune_allocator()  # as every rovergate program does (rovergate/runtime.py)
    logging.basicConfig(level=logging.WARNING)
    session = zenoh.open(zenoh_config(SessionConfig()))
    keys = Keys("rover")
    pubs = {t: session.declare_publisher(keys.key(t))
            for t in ("depth", "camera_info", "pose", "base_pose")}
    print(f"{'scene':<12} {'platform':<8} {'render ms':>9} {'publish ms':>10} {'frames/s':>9} "
          f"{'samples':>8} {'cov. update ms (median / max)':>30}")
    for name in args.scenes:
        for platform in ("rover", "flyer"):
            cfg = MissionConfig(scene=SceneConfig(name=name), platform=platform)
            if args.degraded:
                cfg.sensing = SensingConfig(noise_frac=0.01, dropout_pixel_prob=0.01,
                                            dropout_blob_frac=0.05, grazing_max_deg=80,
                                            drift_xy_m=0.02, drift_yaw_deg=0.3)
            resolve_scene(cfg.scene)
            sim = RoverSim(cfg)
            mapper = Mapper(cfg.mapper)
            evaluator = CoverageEvaluator(sim.truth_surface(), cfg.eval.tau_frac
                                          * cfg.scene.d_scene_m)
            render_s, publish_s, cover_s = [], [], []
            for t in range(args.frames):
                t0 = time.perf_counter()
                frame = sim.render(t)
                t1 = time.perf_counter()
                pubs["depth"].put(encode("depth", (t, frame.depth_m)))
                pubs["camera_info"].put(encode("camera_info", (t, frame.intrinsics)))
                pubs["pose"].put(encode("pose", (t, frame.T_map_camera)))
                pubs["base_pose"].put(encode("base_pose", (t, frame.T_map_base)))
                t2 = time.perf_counter()
                render_s.append(t1 - t0)
                publish_s.append(t2 - t1)
                surface = xyz(mapper.step(frame).surface)
                t3 = time.perf_counter()
                evaluator.update(surface)
                cover_s.append(time.perf_counter() - t3)
                # Turn in place: 18 degrees a frame (state[2] is the rover's yaw, [3] the
                # flyer's).
                s = list(sim.state)
                s[2 if platform == "rover" else 3] += np.radians(18)
                sim.state = tuple(s)
            sim.close()
            r, p = statistics.median(render_s), statistics.median(publish_s)
            print(f"{name:<12} {platform:<8} {1e3 * r:9.1f} {1e3 * p:10.2f} {1 / (r + p):9.1f} "
                  f"{len(evaluator.samples):8d} {1e3 * statistics.median(cover_s):18.1f} / "
                  f"{1e3 * max(cover_s):5.1f}", flush=True)
    session.close()


if __name__ == "__main__":
    main()
