"""Watch a rover's occupancy from another machine: zenoh and rosbags, nothing of rovergate.

    python examples/remote_subscriber.py --connect tcp/ROVER_HOST:7447 --count 5

(start the mission with `rovergate run --listen tcp/0.0.0.0:7447` so that it accepts the
connection). Prints one line per planner-facing map and observed surface it decodes, and
exits after --count maps.
"""

from __future__ import annotations

import argparse
import json
import threading
import time

import numpy as np
import zenoh
from rosbags.typesys import Stores, get_typestore

STORE = get_typestore(Stores.ROS2_HUMBLE)
SOURCES = ("observed", "predicted", "oracle-fn", "truth")


def fields(msg) -> dict[str, np.ndarray]:
    """The PointCloud2's fields as arrays, read from its own layout."""
    kinds = {2: "u1", 4: "<u2", 7: "<f4"}
    n = msg.width * msg.height
    raw = np.frombuffer(msg.data.tobytes(), dtype=np.uint8).reshape(n, msg.point_step)
    out = {}
    for f in msg.fields:
        dt = np.dtype(kinds[f.datatype])
        out[f.name] = raw[:, f.offset:f.offset + dt.itemsize].copy().view(dt)[:, 0]
    return out


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

    def on_map(sample):
        nonlocal maps
        msg = STORE.deserialize_cdr(sample.payload.to_bytes(), "sensor_msgs/msg/PointCloud2")
        f = fields(msg)
        counts = np.bincount(f["source"], minlength=len(SOURCES))
        parts = ", ".join(f"{c} {s}" for s, c in zip(SOURCES, counts, strict=True) if c)
        print(f"planner map step {msg.header.stamp.sec}: {len(f['x'])} points ({parts}); "
              f"encoding {sample.encoding}", flush=True)
        maps += 1
        if maps >= args.count:
            done.set()

    def on_surface(sample):
        msg = STORE.deserialize_cdr(sample.payload.to_bytes(), "sensor_msgs/msg/PointCloud2")
        f = fields(msg)
        print(f"surface step {msg.header.stamp.sec}: {len(f['x'])} points, z "
              f"{f['z'].min():.2f}..{f['z'].max():.2f} m", flush=True)

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
