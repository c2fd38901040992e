"""The live wire under attack, from inside and from outside the rover network.

- Inside: during a mission, a client on the modules' own endpoint (the Unix socket, with full
  rights) sends 10,000 malformed messages over Zenoh across every key the rover's processes
  subscribe to. No process crashes, every message is dropped and counted, and the mission's
  per-step coverage is that of a clean run.
- Outside: a client on the --listen endpoint that other machines use publishes well-formed,
  forged messages (an aborted status, paths, sensor samples, at the current step), declares
  liveliness tokens and queryables, and asks for ground truth, for the whole mission. The
  access control makes it read-only: the mission runs as a clean one, and no truth reaches
  it.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import subprocess
from pathlib import Path

import numpy as np
import pytest
import zenoh
from conftest import RovergateProcess, StatusWatcher, run_cli
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
    mission = RovergateProcess(["run", "--steps", str(steps), "--no-progress", "--out",
                       str(tmp_path / "p"), "--listen", f"tcp/127.0.0.1:{port}",
                       "--contact.no-enabled"])
    inside = mission.wait_for_line(r"the modules connect to (unixsock-stream/\S+);").group(1)
    watcher = StatusWatcher(port)
    session = zenoh.open(zenoh_config(SessionConfig(mode="client", connect=(inside,))))
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


def _forged(topic: str, step: int):
    """A well-formed sample of ``topic`` stamped ``step``: what a module would send."""
    value = VALUES[topic]
    if isinstance(value, tuple):
        return (step, value[1])
    return dataclasses.replace(value, step=step)


def test_a_remote_client_cannot_drive_the_mission(tmp_path: Path):
    """A client on --listen forges the mission's traffic for the whole mission; the mission
    is a clean run's to the last digit, nothing it sent was even counted as dropped (it never
    got past the mission's session), and ground truth never reaches another client there,
    which can still read the rest."""
    steps = 12
    port = free_loopback_port()
    keys = Keys("rover")
    mission = RovergateProcess(["run", "--steps", str(steps), "--no-progress", "--out",
                       str(tmp_path / "p"), "--listen", f"tcp/127.0.0.1:{port}",
                       "--contact.no-enabled"])
    mission.wait_for_line(r"started sim \(pid")  # its session listens before it starts any
    watcher = StatusWatcher(port)  # a reader, beside the attacker
    attacker = zenoh.open(zenoh_config(SessionConfig(mode="client",
                                                     connect=(f"tcp/127.0.0.1:{port}",))))
    forged = [t for t in ("status", "path", "rejected", "execution", "depth", "camera_info",
                          "pose", "base_pose", "surface", "predicted", "planner_map", "timing")
              if t in VALUES]
    sent, read = 0, set()
    try:
        # It poses as the mission and as modules, and serves a journal and truth of its own.
        tokens = [attacker.liveliness().declare_token(keys.alive(m))
                  for m in ("mission", "sim", "planner")]
        queryables = [attacker.declare_queryable(
            key, lambda q, key=key: q.reply(key, b"\x00\x01\x00\x00forged"))
            for key in (keys.journal("depth"), keys.key("truth_surface"))]
        publishers = {t: attacker.declare_publisher(keys.key(t), encoding=cdr_encoding(t))
                      for t in forged}
        while mission.proc.poll() is None:
            step = max(watcher.steps, default=0)
            for s in (step, step + 1):
                publishers["status"].put(encode("status", dataclasses.replace(
                    VALUES["status"], step=s, steps_total=steps, state="aborted")))
                for t in forged[1:]:
                    publishers[t].put(encode(t, _forged(t, s)))
                sent += len(forged)
            if step >= 2 and not read:
                read = {(str(r.ok.key_expr), r.ok.payload.to_bytes()[4:10])
                        for key in (keys.key("truth_surface"), f"{keys.namespace}/**")
                        for r in watcher.session.get(
                            key, timeout=5.0, consolidation=zenoh.ConsolidationMode.NONE)
                        if r.ok is not None}
            with contextlib.suppress(subprocess.TimeoutExpired):
                mission.proc.wait(0.02)  # paced, until the mission ends
        assert mission.finish(60) == 0, mission.text[-4000:]
        for q in queryables:
            q.undeclare()
        for tok in tokens:
            tok.undeclare()
    finally:
        attacker.close()
        watcher.close()
        mission.kill()
    print(f"forged messages sent from --listen: {sent}")  # the README's figure (pytest -s)
    assert sent > 500, sent
    assert not [k for k, _ in read if "/truth/" in k], read
    assert any("/mission/journal/" in k for k, _ in read), read  # reading works
    assert not [k for k, head in read if head == b"forged"], read  # no forged reply passed
    assert watcher.steps[-1] == steps and "aborted" not in watcher.states[:-1]
    attacked = json.loads((tmp_path / "p" / "metrics.json").read_text())
    assert attacked["state"] == "done" and attacked["restarts"] == []
    assert attacked["dropped_messages"] == 0, attacked["dropped_messages"]
    clean = run_cli("run", "--steps", str(steps), "--in-process", "--out", str(tmp_path / "i"),
                    timeout=300)
    assert clean.returncode == 0, clean.stderr[-3000:]
    assert (tmp_path / "p" / "coverage.csv").read_text() == \
        (tmp_path / "i" / "coverage.csv").read_text()
