"""A frontier planner that is not part of rovergate: the example of a planner of your own.

It uses only zenoh, rosbags and numpy, and keeps the planner contract of
docs/writing-a-planner.md:

- subscribe to ``<ns>/map/occupancy/planner`` (rovergate_msgs/CloudUpdate: the map as what
  changed since the step before, made whole by ``examples/cloud_updates.py``) and
  ``<ns>/sensor/base_pose`` (geometry_msgs/PoseStamped);
- for each step t (``header.stamp.sec``) once both have come, publish a nav_msgs/Path of base
  poses on ``<ns>/plan/path``, stamped t, encoded ``application/cdr`` with the type name as
  schema; its first pose is where the rover stands;
- declare the liveliness token ``<ns>/alive/planner`` once subscribed, and stop when
  ``<ns>/mission/status`` says done or aborted.

The strategy: lay the map on a 2D grid, call a cell a frontier when it holds map points and
borders cells that hold none, and drive in a straight line to the best frontier within the
step's budget (frontier size over distance), over cells the map knows and that are not
obstacles (or, within the camera's blind band next to the rover, cells it does not know).
Nothing within reach: turn in place a quarter turn.

    python examples/frontier_planner.py --connect unixsock-stream/PATH --namespace rover

(`rovergate run --planner.command "python examples/frontier_planner.py"` starts it for you
and appends those two flags: the mission's own socket, where modules have full rights.)
"""

from __future__ import annotations

import argparse
import json
import math
import threading

import numpy as np
import zenoh
from cloud_updates import CLOUD_UPDATE, MapStream, register
from rosbags.typesys import Stores, get_typestore

STORE = get_typestore(Stores.ROS2_HUMBLE)
register(STORE)
T = STORE.types
PATH_ENCODING = zenoh.Encoding.APPLICATION_CDR.with_schema("nav_msgs/msg/Path")
CELL_M = 0.5
MAX_STEP_M = 3.0
OBSTACLE_SPAN_M = 0.35
VISITED_M = 1.5
HALF_WIDTH_M = 0.35  # the rover is 0.7 m wide
BLIND_M = 2.5  # the mast camera (1.6 m up, 15 degrees down, 45 degrees field) first sees
#               the ground about 2.1 m ahead


def yaw_of(q) -> float:
    return math.atan2(2 * (q.w * q.z + q.x * q.y), 1 - 2 * (q.y * q.y + q.z * q.z))


def choose_goal(points: np.ndarray, x: float, y: float,
                visited: list[tuple[float, float]],
                blocked: set[tuple[int, int]] = frozenset()) -> tuple[float, float] | None:
    """The best frontier cell within reach along a free straight line, or None. Frontiers
    near where the rover has already stood are skipped (the band of ground next to the rover,
    which its mast camera cannot see, would otherwise hold it in place)."""
    if len(points) == 0:
        return None
    ij = np.floor(points[:, :2] / CELL_M).astype(np.int64)
    lo = ij.min(axis=0) - 1
    ij -= lo
    shape = tuple(ij.max(axis=0) + 2)
    zmin = np.full(shape, np.inf)
    zmax = np.full(shape, -np.inf)
    np.minimum.at(zmin, (ij[:, 0], ij[:, 1]), points[:, 2])
    np.maximum.at(zmax, (ij[:, 0], ij[:, 1]), points[:, 2])
    known = np.isfinite(zmin)
    free = known & (zmax - zmin < OBSTACLE_SPAN_M)
    for bi, bj in blocked:  # where the rover was stopped by something it did not see
        a, b = bi - lo[0], bj - lo[1]
        if 0 <= a < shape[0] and 0 <= b < shape[1]:
            known[a, b], free[a, b] = True, False
    unknown = np.pad(~known, 1, constant_values=True)
    border = sum(unknown[1 + di:1 + di + shape[0], 1 + dj:1 + dj + shape[1]].astype(int)
                 for di in (-1, 0, 1) for dj in (-1, 0, 1) if di or dj)
    frontier = free & (border > 0)
    ci, cj = np.nonzero(frontier)
    if len(ci) == 0:
        return None
    cx = (ci + lo[0] + 0.5) * CELL_M
    cy = (cj + lo[1] + 0.5) * CELL_M
    dist = np.hypot(cx - x, cy - y)
    score = border[ci, cj] / (1.0 + dist)
    if visited:
        been = np.asarray(visited)
        near = np.hypot(cx[:, None] - been[None, :, 0], cy[:, None] - been[None, :, 1])
        score[near.min(axis=1) < VISITED_M] = -1
    for k in np.argsort(-score):
        d = dist[k]
        if score[k] < 0 or d < VISITED_M:
            continue
        # Head for it, at most MAX_STEP_M, if every cell on the way is known and free. Within
        # BLIND_M of the rover a cell may also be unknown (its mast camera cannot see the
        # ground there), but never a known obstacle.
        reach = min(d, MAX_STEP_M)
        gx = x + (cx[k] - x) * reach / d
        gy = y + (cy[k] - y) * reach / d
        ok = True
        ux, uy = (gx - x) / reach, (gy - y) / reach
        for s in np.arange(CELL_M / 2, reach + 1e-9, CELL_M / 2):
            for side in (-HALF_WIDTH_M, 0.0, HALF_WIDTH_M):  # the body's width, not a line
                px, py = x + ux * s - uy * side, y + uy * s + ux * side
                a = int(math.floor(px / CELL_M)) - lo[0]
                b = int(math.floor(py / CELL_M)) - lo[1]
                inside = 0 <= a < shape[0] and 0 <= b < shape[1]
                if inside and free[a, b]:
                    continue
                if s < BLIND_M and not (inside and known[a, b]):
                    continue
                ok = False
                break
            if not ok:
                break
        if ok:
            return gx, gy
    return None


def make_path(step: int, pose, goal: tuple[float, float] | None):
    p, q = pose.position, pose.orientation
    yaw = yaw_of(q)

    def stamped(x, y, heading):
        quat = T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=math.sin(heading / 2),
                                                 w=math.cos(heading / 2))
        return T["geometry_msgs/msg/PoseStamped"](
            header=header(step), pose=T["geometry_msgs/msg/Pose"](
                position=T["geometry_msgs/msg/Point"](x=float(x), y=float(y), z=float(p.z)),
                orientation=quat))

    start = T["geometry_msgs/msg/PoseStamped"](header=header(step), pose=pose)
    if goal is None:
        poses = [start, stamped(p.x, p.y, yaw + math.pi / 2)]
    else:
        heading = math.atan2(goal[1] - p.y, goal[0] - p.x)
        poses = [start, stamped(p.x, p.y, heading), stamped(goal[0], goal[1], heading)]
    return T["nav_msgs/msg/Path"](header=header(step), poses=poses)


def header(step: int):
    return T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](sec=step,
                                                                           nanosec=0),
                                    frame_id="map")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--connect", action="append", default=[])
    ap.add_argument("--namespace", default="rover")
    args = ap.parse_args()
    ns = args.namespace
    conf = zenoh.Config()
    conf.insert_json5("mode", '"client"')  # a client of the mission's session, as modules are
    conf.insert_json5("connect/endpoints", json.dumps(args.connect))
    conf.insert_json5("scouting/multicast/enabled", "false")
    session = zenoh.open(conf)
    maps: dict[int, np.ndarray] = {}
    poses: dict[int, object] = {}
    done = threading.Event()
    lock = threading.Lock()
    publisher = session.declare_publisher(f"{ns}/plan/path", encoding=PATH_ENCODING)
    planned: set[int] = set()
    visited: list[tuple[float, float]] = []
    blocked: set[tuple[int, int]] = set()
    intended: dict[int, tuple[float, float, float, float]] = {}  # step -> start and goal

    def try_plan() -> None:
        with lock:
            last = max(planned, default=-1)
            ready = sorted(s for s in set(maps) & set(poses) if s > last)
            for step in ready:
                pose = poses[step]
                x, y = pose.position.x, pose.position.y
                visited.append((x, y))
                before = intended.get(step - 1)
                if before is not None and math.hypot(x - before[0], y - before[1]) < 0.5 * \
                        math.hypot(before[2] - before[0], before[3] - before[1]):
                    # Stopped well short of the last goal: something it did not see stands
                    # just ahead of where it is now. Never drive into that cell again.
                    heading = math.atan2(before[3] - before[1], before[2] - before[0])
                    blocked.add((int(math.floor((x + 0.8 * math.cos(heading)) / CELL_M)),
                                 int(math.floor((y + 0.8 * math.sin(heading)) / CELL_M))))
                goal = choose_goal(maps[step], x, y, visited, blocked)
                if goal is not None:
                    intended[step] = (x, y, *goal)
                path = make_path(step, pose, goal)
                publisher.put(bytes(STORE.serialize_cdr(path, "nav_msgs/msg/Path")))
                planned.add(step)
                where = f"to ({goal[0]:.1f}, {goal[1]:.1f})" if goal else "turning in place"
                print(f"frontier planner: step {step}: {where}", flush=True)
            for old in [s for s in maps if s < max(planned, default=0) - 2]:
                maps.pop(old, None)
                poses.pop(old, None)

    stream = MapStream()  # the map travels as what changed since the step before

    def on_map(sample):
        msg = STORE.deserialize_cdr(sample.payload.to_bytes(), CLOUD_UPDATE)
        with lock:
            for step in stream.offer(msg):
                maps[step] = stream.xyz()
        try_plan()

    def on_pose(sample):
        msg = STORE.deserialize_cdr(sample.payload.to_bytes(), "geometry_msgs/msg/PoseStamped")
        with lock:
            poses[msg.header.stamp.sec] = msg.pose
        try_plan()

    def on_status(sample):
        msg = STORE.deserialize_cdr(sample.payload.to_bytes(), "rovergate_msgs/msg/MissionStatus")
        if msg.state in ("done", "aborted"):
            done.set()

    register_status_type()
    subs = [session.declare_subscriber(f"{ns}/map/occupancy/planner", on_map),
            session.declare_subscriber(f"{ns}/sensor/base_pose", on_pose),
            session.declare_subscriber(f"{ns}/mission/status", on_status)]
    # Started in the middle of a step (a restart after a crash), the map of that step was
    # sent before we listened: the mission's journal holds the last few. Steps that already
    # have a path (the journal has those too) are not planned again.
    for reply in session.get(f"{ns}/mission/journal/plan/path?from=0;to=2147483647",
                             timeout=5.0, consolidation=zenoh.ConsolidationMode.NONE):
        if reply.ok is not None:
            msg = STORE.deserialize_cdr(reply.ok.payload.to_bytes(), "nav_msgs/msg/Path")
            planned.add(msg.header.stamp.sec)
    for key, handler in ((f"{ns}/mission/journal/map/occupancy/planner", on_map),
                         (f"{ns}/mission/journal/sensor/base_pose", on_pose)):
        for reply in session.get(f"{key}?from=0;to=2147483647", timeout=5.0,
                                 consolidation=zenoh.ConsolidationMode.NONE):
            if reply.ok is not None:
                handler(reply.ok)
    token = session.liveliness().declare_token(f"{ns}/alive/planner")
    print(f"frontier planner: ready on {', '.join(args.connect)} ({ns})", flush=True)
    done.wait()
    token.undeclare()
    for s in subs:
        s.undeclare()
    session.close()


STATUS_MSG = """std_msgs/Header header
uint32 step
uint32 steps_total
string state
string condition
float64 coverage
uint32 collisions
"""


def register_status_type() -> None:
    """The mission's status is a rovergate type: declare it to rosbags from its definition."""
    from rosbags.typesys import get_types_from_msg
    STORE.register(get_types_from_msg(STATUS_MSG, "rovergate_msgs/msg/MissionStatus"))


if __name__ == "__main__":
    main()
