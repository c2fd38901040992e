"""The node runtime on real Zenoh sessions: lockstep, and bad input dropped but counted."""

from __future__ import annotations

import logging
import threading

import pytest
from conftest import Waiter

from rovergate.config import SessionConfig
from rovergate.graph import Input, Module
from rovergate.messages import encode
from rovergate.module import LogicDefaults, StepOutput
from rovergate.node import ModuleNode, cdr_encoding
from rovergate.types import MissionStatus, Pose

#: A module of the test's own: base poses in, the tick of the step before as a lagged input.
SPEC = Module("probe", "a test module", inputs={"base": Input("base_pose"),
                                                "tick": Input("status", lag=1)},
              outputs=("path",))


class Probe(LogicDefaults):
    spec = SPEC

    def __init__(self, waiter: Waiter) -> None:
        self.handled: list[tuple[int, bool]] = []
        self.waiter = waiter

    def handle(self, step, inputs):
        with self.waiter.cv:
            self.handled.append((step, inputs["tick"] is not None))
            self.waiter.cv.notify_all()
        return StepOutput()


def _wait_matched(session, key: str) -> None:
    """Wait until a subscriber of ``key`` is known to ``session`` (a matching listener)."""
    matched = threading.Event()
    publisher = session.declare_publisher(key)
    listener = publisher.declare_matching_listener(
        lambda status: matched.set() if status.matching else None)
    if publisher.matching_status.matching:
        matched.set()
    assert matched.wait(30), f"no subscriber matched {key} within 30 s"
    listener.undeclare()
    publisher.undeclare()


def test_node_drops_malformed_messages_and_runs_on(loopback_pair):
    endpoint, hub, _ = loopback_pair
    node = ModuleNode(SPEC, SessionConfig(connect=(endpoint,)), logging.getLogger("test"))
    waiter = Waiter()
    probe = Probe(waiter)
    result: list[str] = []
    thread = threading.Thread(target=lambda: result.append(node.spin(probe, 30.0)))
    thread.start()
    try:
        key, enc = "rover/sensor/base_pose", cdr_encoding("base_pose")
        for k in (key, "rover/mission/status"):  # wait until the node's subscriptions are known
            _wait_matched(hub, k)
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
        waiter.wait_for(lambda: len(probe.handled) >= 3, 30, "three handled steps")
        hub.put("rover/mission/status", encode("status", MissionStatus(3, 5, "done", "obs", 0, 0)),
                encoding=cdr_encoding("status"))
        thread.join(30)
    finally:
        node.close()
    assert result == ["done"]
    assert node.dropped == 3
    # Step 0 needs no tick (lag 1); steps 1 and 2 need the ticks of steps 0 and 1.
    assert probe.handled == [(0, False), (1, True), (2, True)]


class _Sample:
    """What a zenoh sample offers a callback: an encoding and a payload."""

    def __init__(self, topic: str, payload: bytes, encoding=None) -> None:
        self.encoding = encoding if encoding is not None else cdr_encoding(topic)
        self.payload = type("P", (), {"to_bytes": lambda _self: payload})()


def test_the_step_of_a_journalled_message_is_read_from_its_header():
    """The mission reads only the step of what it merely journals; it is the step decode
    gives, and bytes that are not the topic's CDR are refused as decode refuses them."""
    import numpy as np
    import pytest

    from rovergate.messages import MessageError, decode
    from rovergate.node import stamp_of
    from rovergate.types import CameraIntrinsics
    values = {"depth": (7, np.ones((4, 5), np.float32)),
              "camera_info": (8, CameraIntrinsics.from_fov(160, 120, 45.0)),
              "pose": (9, Pose.from_xyz_yaw(1, 2, 3, 0.5))}
    for topic, value in values.items():
        payload = encode(topic, value)
        assert stamp_of(topic, _Sample(topic, payload)) == decode(topic, payload)[0] == value[0]
    with pytest.raises(MessageError, match="encoding"):
        stamp_of("depth", _Sample("pose", encode("pose", values["pose"])))
    with pytest.raises(MessageError, match="CDR"):
        stamp_of("depth", _Sample("depth", b"\x01\x00"))


def test_a_flood_of_bad_messages_is_counted_whole_and_logged_sparsely(caplog):
    import logging

    from rovergate.logs import DROP_LOG_EVERY, DROP_LOG_FIRST, log_drop
    log = logging.getLogger("rovergate.test-drops")
    with caplog.at_level(logging.WARNING, logger=log.name):
        for count in range(1, 5001):
            log_drop(log, count, "message", "rover/x", "garbage")
    lines = [r.getMessage() for r in caplog.records]
    assert len(lines) == DROP_LOG_FIRST + 5000 // DROP_LOG_EVERY
    assert lines[0].endswith("(1 dropped so far)")
    assert lines[-1].endswith("(5000 dropped so far; logging one in 1000)")


def test_a_launched_modules_command_line_reads_as_tyro_reads_it(tmp_path):
    """The process set starts each module with ``--config FILE`` and session flags; the
    module reads that command line without tyro (start-up time), to the same config, and any
    other command line goes to tyro."""
    import dataclasses

    from mission.runtime.flags import launched_config as _launched_config
    from mission.runtime.flags import mission_config as _mission_config
    from rovergate.config import MissionConfig, save_config
    path = tmp_path / "config.json"
    save_config(dataclasses.replace(MissionConfig(steps=7, condition="gated"), out=tmp_path),
                path)
    argv = ["--config", str(path), "--mode", "client", "--connect", "unixsock-stream//tmp/x.sock",
            "--listen", "--namespace", "ns2", "--wait-for-peers", "1"]
    fast = _launched_config(argv)
    assert fast is not None and fast == _mission_config("mapper", argv)
    assert fast.session.mode == "client" and fast.session.listen == ()
    assert fast.session.connect == ("unixsock-stream//tmp/x.sock",) and fast.steps == 7
    # A restarted module's flags and a user's own go to tyro.
    for other in (argv + ["--steps", "9"], argv[:2] + ["--mode", "bogus"],
                  argv[:2] + ["--wait-for-peers", "x"], argv[:2] + ["--mode"],
                  ["--steps", "3"], argv + ["--mode", "peer"]):
        assert _launched_config(other) is None


def test_a_query_is_asked_again_until_an_answer_decodes_and_times_out_in_its_own_words(
        loopback_pair, caplog):
    from rovergate.node import ask_until_answered
    _, server, client = loopback_pair
    asked: list[str] = []

    def on_query(query):
        asked.append(str(query.attachment.to_string()) if query.attachment else "")
        if len(asked) == 1:  # the first answer is garbage, with the right encoding
            query.reply(query.key_expr, b"\x00\x01garbage", encoding=cdr_encoding("status"))
        else:
            query.reply(query.key_expr, encode("status", MissionStatus(4, 9, "running", "obs",
                                                                       0.5, 0)),
                        encoding=cdr_encoding("status"))
    queryable = server.declare_queryable("rover/mission/status", on_query)
    log = logging.getLogger("test.ask")
    with caplog.at_level(logging.WARNING, "test.ask"):
        value = ask_until_answered(client, "rover/mission/status", "status", "planner", 60, log)
    assert (value.step, value.steps_total, value.coverage) == (4, 9, 0.5)
    assert asked[:2] == ["planner", "planner"]  # asked twice, as the caller
    assert "dropped a reply on rover/mission/status" in caplog.text
    queryable.undeclare()
    checks: list[int] = []
    with pytest.raises(TimeoutError, match="rover/nothing/here"):
        ask_until_answered(client, "rover/nothing/here", "status", "mission", 0.5, log,
                           before_each=lambda: checks.append(1))
    assert checks  # the caller's check ran before each try
