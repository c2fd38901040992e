"""Benchmark: the bag's bytes per step, by topic, over a mission's course (issue 30).

Runs one recorded mission (default flags but ``--steps``; in process unless ``--processes``),
then reads its bag and prints, for each fifth of the mission, the bag bytes per step (the
messages' bytes by their step, and the file's bytes over all steps), each topic's share, and
what the incremental maps would have cost as whole clouds (each step's map made whole again
and encoded as the ``sensor_msgs/msg/PointCloud2`` every step used to be), with the ratio.
The issue's bar: at most 0.5 MB a step over the last fifth of a 300-step mission.

Usage: .venv/bin/python benchmarks/bench_bag.py [--steps 300] [--processes]
           [--keyframe-every 25] [--condition obs] [--out DIR]
"""

from __future__ import annotations

import argparse
import itertools
import logging
import tempfile
from collections import defaultdict
from pathlib import Path

from rosbags.rosbag2 import Reader

from mission.runtime.loop import run_in_process, run_processes
from rover_sim.catalog import resolve_scene
from rovergate.config import MissionConfig, SessionConfig
from rovergate.keys import Keys
from rovergate.messages import cloud_cdr, decode
from rovergate.runtime import tune_allocator
from rovergate.streams import INCREMENTAL, StreamDecoder
from rovergate.types import PlannerMap

MB = 1e6


def bag_bytes(bag: Path, namespace: str = "rover") -> tuple[dict[str, dict[int, int]],
                                                            dict[str, dict[int, int]]]:
    """Per topic and step: the bytes of its messages in the bag, and for the incremental maps
    the bytes the whole cloud of that step takes as a PointCloud2."""
    keys = Keys(namespace)
    names = {"/" + keys.key(t): t for t in keys_of_bag()}
    sent: dict[str, dict[int, int]] = defaultdict(lambda: defaultdict(int))
    whole: dict[str, dict[int, int]] = defaultdict(dict)
    decoders = {t: StreamDecoder(t) for t in INCREMENTAL}
    with Reader(bag) as reader:
        for conn, _, data in reader.messages():
            topic = names.get(conn.topic, conn.topic)
            raw = bytes(data)
            step = int.from_bytes(raw[4:8], "little", signed=True)  # header.stamp.sec
            sent[topic][step] += len(raw)
            if topic in decoders:
                for s, value in decoders[topic].offer(decode(topic, raw)[1]):
                    cloud = value.points if isinstance(value, PlannerMap) else value
                    whole[topic][s] = len(cloud_cdr(s, cloud))
    return sent, whole


def keys_of_bag() -> list[str]:
    from rovergate.taps import tapped_topics
    return list(tapped_topics())


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=300)
    ap.add_argument("--processes", action="store_true", help="run the process set")
    ap.add_argument("--keyframe-every", type=int, default=SessionConfig.keyframe_every)
    ap.add_argument("--condition", default=MissionConfig.condition)
    ap.add_argument("--out", type=Path, default=None, help="keep the mission here")
    args = ap.parse_args()
    logging.basicConfig(level=logging.WARNING)
    tune_allocator()
    out = args.out or Path(tempfile.mkdtemp(prefix="bench-bag-"))
    cfg = MissionConfig(steps=args.steps, out=out, progress=False, condition=args.condition,
                        in_process=not args.processes,
                        session=SessionConfig(keyframe_every=args.keyframe_every))
    resolve_scene(cfg.scene)
    (run_processes if args.processes else run_in_process)(cfg)
    bag = out / "bag"
    sent, whole = bag_bytes(bag)
    file_bytes = sum(p.stat().st_size for p in bag.iterdir())
    steps = args.steps
    print(f"mission: {steps} steps, {args.condition}, "
          f"{'process set' if args.processes else 'in process'}, "
          f"keyframe every {args.keyframe_every}; bag {file_bytes / MB:.1f} MB "
          f"({file_bytes / MB / (steps + 1):.3f} MB a step over the whole mission)")
    edges = [round(i * (steps + 1) / 5) for i in range(6)]  # steps 0..steps in fifths
    blocks = [(a, b) for a, b in itertools.pairwise(edges) if b > a]
    topics = sorted(sent, key=lambda t: -sum(sent[t].values()))
    print("\nbag bytes per step (MB), by step block; 'as whole': the incremental maps sent "
          "whole every step")
    print(f"{'steps':>11} {'sent':>7} {'as whole':>9} {'ratio':>6}   largest topics (MB a step)")
    for a, b in blocks:
        n = b - a
        total = sum(v for t in topics for s, v in sent[t].items() if a <= s < b) / n
        as_whole = total + sum(
            whole[t].get(s, 0) - sent[t].get(s, 0) for t in INCREMENTAL for s in range(a, b)
        ) / n
        per = {t: sum(v for s, v in sent[t].items() if a <= s < b) / n for t in topics}
        top = ", ".join(f"{t} {v / MB:.3f}" for t, v in
                        sorted(per.items(), key=lambda kv: -kv[1])[:4])
        print(f"{a:>5}-{b - 1:<5} {total / MB:>7.3f} {as_whole / MB:>9.3f} "
              f"{as_whole / max(total, 1):>6.1f}   {top}")
    a, b = blocks[-1]
    last = sum(v for t in topics for s, v in sent[t].items() if a <= s < b) / (b - a)
    print(f"\nlast fifth: {last / MB:.3f} MB a step (bar: at most 0.5)")


if __name__ == "__main__":
    main()
