"""The live wire under attack: during a mission, a client on its --listen endpoint sends
10,000 malformed messages over Zenoh across every key the rover's processes subscribe to.
No process crashes, every message is dropped and counted, and the mission's per-step
coverage is that of a clean run."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import zenoh
from conftest import Mission, StatusWatcher, run_cli
from test_messages import VALUES

from rovergate.config import SessionConfig
from rovergate.graph import MODULES
from rovergate.keys import Keys
from rovergate.messages import encode
from rovergate.node import cdr_encoding
from rovergate.session import free_loopback_port, zenoh_config

pytestmark = pytest.mark.e2e

MESSAGES = 10_000


def malformed(rng: np.random.Generator, topic: str, i: int) -> tuple[bytes, zenoh.Encoding]:
    """The i-th bad message for ``topic``: random bytes, a valid message cut short or with
    bytes flipped (under the topic's own encoding), or a valid one under a wrong type."""
    kind = i % 4
    if kind == 0:
        return rng.bytes(int(rng.integers(0, 300))), cdr_encoding(topic)
    wire = bytearray(encode(topic, VALUES[topic]))
    if kind == 1:
        return bytes(wire[:int(rng.integers(0, max(len(wire) // 2, 1)))]), cdr_encoding(topic)
    if kind == 2:  # a flipped header byte: an impossible field, length or type
        wire[4:8] = rng.bytes(4)
        wire[-4:] = b"\xff\xff\xff\x7f"
        return bytes(wire[:len(wire) // 2]), cdr_encoding(topic)
    return bytes(wire), zenoh.Encoding.APPLICATION_CDR.with_schema("std_msgs/msg/String")


def test_ten_thousand_malformed_messages_change_no_number(tmp_path: Path):
    steps = 12
    port = free_loopback_port()
    keys = Keys("rover")
    topics = sorted({i.topic for m in MODULES.values() for i in m.inputs.values()
                     if i.topic in VALUES})
    mission = Mission(["run", "--steps", str(steps), "--no-progress", "--out",
                       str(tmp_path / "p"), "--listen", f"tcp/127.0.0.1:{port}",
                       "--contact.no-enabled"])
    mission.wait_for_line(r"started sim \(pid")  # its session listens before it starts any
    watcher = StatusWatcher(port)
    session = zenoh.open(zenoh_config(SessionConfig(mode="client",
                                                    connect=(f"tcp/127.0.0.1:{port}",))))
    try:
        watcher.wait_step(2)
        rng = np.random.default_rng(7)
        publishers = {t: session.declare_publisher(keys.key(t)) for t in topics}
        for i in range(MESSAGES):
            topic = topics[i % len(topics)]
            payload, encoding = malformed(rng, topic, i // len(topics))
            publishers[topic].put(payload, encoding=encoding)
        assert mission.finish(300) == 0, mission.text[-4000:]
    finally:
        session.close()
        watcher.close()
        mission.kill()
    fuzzed = json.loads((tmp_path / "p" / "metrics.json").read_text())
    assert fuzzed["state"] == "done" and fuzzed["restarts"] == []
    # Each message reached at least one subscriber (most reach several), and each is counted.
    assert fuzzed["dropped_messages"] >= MESSAGES, fuzzed["dropped_messages"]
    clean = run_cli("run", "--steps", str(steps), "--in-process", "--out", str(tmp_path / "i"),
                    timeout=300)
    assert clean.returncode == 0, clean.stderr[-3000:]
    i = json.loads((tmp_path / "i" / "metrics.json").read_text())
    assert fuzzed["coverage"] == i["coverage"]
