"""Watch a rover's occupancy from another machine: zenoh and rosbags, nothing of rovergate.

    python examples/remote_subscriber.py --connect tcp/ROVER_HOST:7447 --count 5

(start the mission with `rovergate run --listen tcp/0.0.0.0:7447` so that it accepts the
connection). Prints one line per planner-facing map and observed surface it decodes, and
exits after --count maps. Both maps travel as what changed since the step before
(examples/cloud_updates.py makes them whole), so the first line comes with the first
keyframe, within 25 steps.
"""

from __future__ import annotations

import argparse
import json
import threading
import time

import numpy as np
import zenoh
from cloud_updates import CLOUD_UPDATE, MapStream, register
from rosbags.typesys import Stores, get_typestore

STORE = get_typestore(Stores.ROS2_HUMBLE)
register(STORE)
SOURCES = ("observed", "predicted", "oracle-fn", "truth")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--connect", action="append", required=True)
    ap.add_argument("--namespace", default="rover")
    ap.add_argument("--count", type=int, default=5, help="exit after this many maps")
    ap.add_argument("--timeout-s", type=float, default=120.0)
    args = ap.parse_args()
    conf = zenoh.Config()
    conf.insert_json5("mode", '"client"')
    conf.insert_json5("connect/endpoints", json.dumps(args.connect))
    conf.insert_json5("scouting/multicast/enabled", "false")
    deadline = time.monotonic() + args.timeout_s
    while True:  # the rover may not be listening yet
        try:
            session = zenoh.open(conf)
            break
        except zenoh.ZError as exc:
            if time.monotonic() > deadline:
                raise SystemExit(f"could not connect to {args.connect}: {exc}") from None
            time.sleep(0.5)
    maps = 0
    done = threading.Event()

    # Both maps travel as what changed since the step before, whole every few steps: until
    # the first whole one (a keyframe) comes, there is nothing to show.
    planner_map, surface = MapStream(), MapStream()

    def on_map(sample):
        nonlocal maps
        msg = STORE.deserialize_cdr(sample.payload.to_bytes(), CLOUD_UPDATE)
        for step in planner_map.offer(msg):
            counts = np.bincount(planner_map.field("source"), minlength=len(SOURCES))
            parts = ", ".join(f"{c} {s}" for s, c in zip(SOURCES, counts, strict=True) if c)
            sent = ("whole" if msg.base_step < 0 else
                    f"{len(msg.put_at)} new, {len(msg.patch_at)} patched")
            print(f"planner map step {step}: {len(planner_map.rows)} points ({parts}; this "
                  f"message {sent}); encoding {sample.encoding}", flush=True)
            maps += 1
            if maps >= args.count:
                done.set()

    def on_surface(sample):
        msg = STORE.deserialize_cdr(sample.payload.to_bytes(), CLOUD_UPDATE)
        for step in surface.offer(msg):
            z = surface.field("z")
            print(f"surface step {step}: {len(z)} points, z {z.min():.2f}..{z.max():.2f} m",
                  flush=True)

    ns = args.namespace
    subs = [session.declare_subscriber(f"{ns}/map/occupancy/planner", on_map),
            session.declare_subscriber(f"{ns}/map/surface", on_surface)]
    ok = done.wait(args.timeout_s)
    for s in subs:
        s.undeclare()
    session.close()
    raise SystemExit(0 if ok else f"only {maps} maps within {args.timeout_s:.0f} s")


if __name__ == "__main__":
    main()
