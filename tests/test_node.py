"""The node runtime on real Zenoh sessions: lockstep, and bad input dropped but counted."""

from __future__ import annotations

import logging
import threading
import time

from rovergate.messages import encode
from rovergate.node import Input, ModuleNode, cdr_encoding
from rovergate.session import SessionConfig
from rovergate.types import MissionStatus, Pose


def test_node_drops_malformed_messages_and_runs_on(loopback_pair):
    endpoint, hub, _ = loopback_pair
    node = ModuleNode("planner", SessionConfig(connect=(endpoint,)),
                      inputs={"base": Input("base_pose"), "tick": Input("status", lag=1)},
                      outputs=["path"], log=logging.getLogger("test"))
    handled: list[tuple[int, bool]] = []
    result: list[str] = []

    def handler(step, inputs):
        handled.append((step, inputs["tick"] is not None))
        return {}

    thread = threading.Thread(target=lambda: result.append(node.spin(handler, 30.0)))
    thread.start()
    try:
        key, enc = "rover/sensor/base_pose", cdr_encoding("base_pose")
        for k in (key, "rover/mission/status"):  # wait until the node's subscriptions are known
            publisher = hub.declare_publisher(k)
            deadline = time.monotonic() + 30
            while not publisher.matching_status.matching:
                assert time.monotonic() < deadline, f"no subscriber matched {k}"
                time.sleep(0.01)
            publisher.undeclare()
        hub.put(key, b"\x00\x01\x00\x00not a pose", encoding=enc)                    # garbage
        hub.put(key, encode("base_pose", (0, Pose.from_xyz_yaw(0, 0, 0, 0))))         # no schema
        hub.put(key, encode("status", MissionStatus(0, 5, "running", "obs", 0, 0)),
                encoding=enc)                                                           # wrong type
        for step in range(3):
            hub.put(key, encode("base_pose", (step, Pose.from_xyz_yaw(step, 0, 0, 0))),
                    encoding=enc)
            hub.put("rover/mission/status",
                    encode("status", MissionStatus(step, 5, "running", "obs", 0.0, 0)),
                    encoding=cdr_encoding("status"))
        deadline = time.monotonic() + 30
        while len(handled) < 3 and time.monotonic() < deadline:
            time.sleep(0.01)
        hub.put("rover/mission/status", encode("status", MissionStatus(3, 5, "done", "obs", 0, 0)),
                encoding=cdr_encoding("status"))
        thread.join(30)
    finally:
        node.close()
    assert result == ["done"]
    assert node.dropped == 3
    # Step 0 needs no tick (lag 1); steps 1 and 2 need the ticks of steps 0 and 1.
    assert handled == [(0, False), (1, True), (2, True)]

