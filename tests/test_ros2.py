"""The ROS 2 graph over rmw_zenoh (issue 17, part 3), without a ROS installation: keys,
attachments and liveliness tokens against rmw_zenoh's design document (docs/design.md, the
version with the 33-byte attachment), and a subscriber written from that document alone that
receives the planner map from a running mission through a Zenoh router."""

from __future__ import annotations

import json
import struct
import threading
from pathlib import Path

import numpy as np
import pytest
import xxhash
import zenoh
from mcap.records import Schema
from mcap_ros2.decoder import DecoderFactory
from rosbags.typesys import Stores, get_typestore

from ecosystem import ros2
from ecosystem.replay import _await_subscriber
from rovergate.messages import TYPESTORE, encode
from rovergate.session import free_loopback_port
from rovergate.streams import Wholes
from rovergate.types import PLANNER_DTYPE
from tests.conftest import Waiter

STRING_HASH = "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18"


def test_data_keys_are_the_design_documents():
    # design.md, "Topic and service name mapping to Zenoh key expressions".
    assert ros2.type_hash("std_msgs/msg/String") == STRING_HASH
    assert ros2.data_key(0, "/chatter", "std_msgs/msg/String") == \
        f"0/chatter/std_msgs::msg::dds_::String_/{STRING_HASH}"
    assert ros2.data_key(0, "/robot1/chatter", "std_msgs/msg/String") == \
        f"0/robot1/chatter/std_msgs::msg::dds_::String_/{STRING_HASH}"
    assert ros2.dds_type("sensor_msgs/msg/PointCloud2") == \
        "sensor_msgs::msg::dds_::PointCloud2_"


def test_liveliness_tokens_are_the_design_documents():
    # design.md, "Graph cache": its node and publisher examples, to the character.
    assert ros2.node_token(2, "aac3178e146ba6f1fc6e6a4085e77f21", 0, "/", "listener") == \
        "@ros2_lv/2/aac3178e146ba6f1fc6e6a4085e77f21/0/0/NN/%/%/listener"
    assert ros2.publisher_token(2, "8b20917502ee955ac4476e0266340d5c", 0, 10, "/", "talker",
                                "/chatter", "std_msgs/msg/String", qos="::,7:,:,:,,") == (
        "@ros2_lv/2/8b20917502ee955ac4476e0266340d5c/0/10/MP/%/%/talker/%chatter/"
        f"std_msgs::msg::dds_::String_/{STRING_HASH}/::,7:,:,:,,")
    assert ros2.mangle("/rover/map/occupancy/planner") == "%rover%map%occupancy%planner"


def test_the_attachment_is_33_bytes_in_the_documents_order():
    gid = bytes(range(0x10, 0x20))
    data = ros2.attachment(1, 1_700_000_000_123_456_789, gid)
    assert data.hex(" ") == ("01 00 00 00 00 00 00 00 15 cd 85 3d fe 9c 97 17 10 "
                             "10 11 12 13 14 15 16 17 18 19 1a 1b 1c 1d 1e 1f")
    assert ros2.parse_attachment(data) == (1, 1_700_000_000_123_456_789, gid)
    with pytest.raises(ValueError):
        ros2.attachment(1, 0, b"short")


def _rmw_zenoh_gid(token: str) -> bytes:
    """An entity's GID as rmw_zenoh's liveliness_utils.cpp makes it, from the xxhash package:
    XXH3-128 of the token, its ``low64`` then its ``high64`` copied in (``memcpy``, so
    little-endian on ROS 2's platforms)."""
    h = xxhash.xxh3_128(token.encode()).intdigest()
    return struct.pack("<QQ", h & 0xFFFF_FFFF_FFFF_FFFF, h >> 64)


def test_a_publishers_gid_is_rmw_zenohs_xxh3_128_of_its_token():
    # XXH3-128 of nothing is 99aa06d3014798d8_6001c324468d497f (xxHash's own test vector).
    assert ros2.gid_of("") == bytes.fromhex("7f498d4624c30160d8984701d306aa99")
    token = ros2.publisher_token(0, "8b20917502ee955ac4476e0266340d5c", 0, 1, "/rover",
                                 ros2.NODE_NAME, "/rover/map/occupancy/planner",
                                 "sensor_msgs/msg/PointCloud2")
    assert ros2.gid_of(token) == _rmw_zenoh_gid(token)
    assert len({ros2.gid_of(token), ros2.gid_of(token.replace("/1/MP", "/2/MP"))}) == 2


def _planner_publisher_token(ros: zenoh.Session) -> str:
    """The liveliness token of the planner map's publisher, as the ROS 2 graph sees it."""
    tokens = [str(r.ok.key_expr) for r in ros.liveliness().get("@ros2_lv/0/**", timeout=10)
              if r.ok]
    (token,) = [t for t in tokens if t.split("/")[5] == "MP"
                and t.split("/")[9] == "%rover%map%occupancy%planner"]
    return token


def _ros_decoder(msgtype: str):
    """A CDR decoder built from the type's ROS 2 definition (mcap-ros2-support; the text
    from rosbags' own Jazzy-era store, not from rovergate)."""
    text, _ = get_typestore(Stores.ROS2_HUMBLE).generate_msgdef(msgtype, ros_version=2)
    return DecoderFactory().decoder_for("cdr", Schema(id=1, name=msgtype, encoding="ros2msg",
                                                      data=text.encode()))


def _configs(endpoint: str) -> tuple[zenoh.Config, zenoh.Config]:
    """A Zenoh router on ``endpoint`` (standing in for rmw_zenohd) and a client of it (the
    ROS 2 side's subscriber)."""
    router_conf = zenoh.Config()
    router_conf.insert_json5("mode", '"router"')
    router_conf.insert_json5("listen/endpoints", json.dumps([endpoint]))
    router_conf.insert_json5("scouting/multicast/enabled", "false")
    client_conf = zenoh.Config()
    client_conf.insert_json5("mode", '"client"')
    client_conf.insert_json5("connect/endpoints", json.dumps([endpoint]))
    client_conf.insert_json5("scouting/multicast/enabled", "false")
    return router_conf, client_conf


class Received:
    def __init__(self) -> None:
        self.samples: list[tuple[str, bytes, bytes | None]] = []
        self.waiter = Waiter()

    def __call__(self, sample: zenoh.Sample) -> None:
        attachment = sample.attachment.to_bytes() if sample.attachment is not None else None
        with self.waiter.cv:
            self.samples.append((str(sample.key_expr), sample.payload.to_bytes(), attachment))
            self.waiter.cv.notify_all()


@pytest.mark.e2e
def test_a_ros2_subscriber_receives_the_planner_map_through_a_router(launch, tmp_path: Path):
    endpoint = f"tcp/127.0.0.1:{free_loopback_port()}"
    router_conf, client_conf = _configs(endpoint)
    received = Received()
    samples, waiter = received.samples, received.waiter
    with zenoh.open(router_conf), zenoh.open(client_conf) as ros:
        sub = ros.declare_subscriber("0/rover/map/occupancy/planner/**", received)
        mission = launch("run", "--ros2", "--ros2-router", endpoint, "--steps", "300",
                         "--platform", "flyer", "--out", str(tmp_path / "run"))
        waiter.wait_for(lambda: len(samples) >= 3, 180, "three planner maps on the ROS 2 key",
                        lambda: "; mission stderr:\n" + "".join(mission.lines[-20:]))
        tokens = [str(r.ok.key_expr) for r in ros.liveliness().get("@ros2_lv/0/**",
                                                                   timeout=10) if r.ok]
        mission.kill()
        sub.undeclare()
    key, payload, attachment = samples[0]
    assert key == ("0/rover/map/occupancy/planner/sensor_msgs::msg::dds_::PointCloud2_/"
                   + ros2.type_hash("sensor_msgs/msg/PointCloud2"))
    # The attachment: sequence numbers from 1, one publisher GID, 33 bytes each.
    parsed = [struct.unpack_from("<qqB", a) + (a[17:],) for _, _, a in samples[:3]]
    assert all(len(a) == 33 for _, _, a in samples[:3])
    assert [p[0] for p in parsed] == [1, 2, 3]
    assert {p[2] for p in parsed} == {16} and len({p[3] for p in parsed}) == 1
    cloud = _ros_decoder("sensor_msgs/msg/PointCloud2")(payload)
    assert [f.name for f in cloud.fields] == ["x", "y", "z", "source", "views", "channels"]
    n = cloud.width * cloud.height
    assert n > 0 and len(cloud.data) == n * cloud.point_step
    xyz = np.frombuffer(bytes(cloud.data), np.uint8).reshape(n, cloud.point_step)[:, :12]
    assert np.isfinite(xyz.copy().view("<f4")).all()
    # The graph: the bridge's node and a publisher of the topic, as `ros2 topic list` reads it.
    nodes = [t for t in tokens if t.split("/")[5] == "NN"]
    publishers = [t for t in tokens if t.split("/")[5] == "MP"
                  and t.split("/")[9] == "%rover%map%occupancy%planner"]
    assert [t.split("/")[7:9] for t in nodes] == [["%rover", "rovergate_bridge"]]
    assert len(publishers) == 1
    assert publishers[0].split("/")[10:] == [
        "sensor_msgs::msg::dds_::PointCloud2_",
        ros2.type_hash("sensor_msgs/msg/PointCloud2"), ros2.QOS_KEEP_LAST_10]
    assert {p[3] for p in parsed} == {_rmw_zenoh_gid(publishers[0])}


@pytest.mark.e2e
def test_a_replay_reaches_the_ros2_graph_with_its_own_sequence(launch, tmp_path: Path):
    from rosbags.rosbag2 import Reader

    from tests.conftest import recorded_mission
    out = tmp_path / "run"
    recorded_mission(out, 3)
    with Reader(out / "bag") as reader:
        maps = [bytes(d) for c, _, d in reader.messages()
                if c.topic == "/rover/map/occupancy/planner"]
    endpoint = f"tcp/127.0.0.1:{free_loopback_port()}"
    router_conf, client_conf = _configs(endpoint)
    received = Received()
    with zenoh.open(router_conf), zenoh.open(client_conf) as ros:
        sub = ros.declare_subscriber("0/rover/map/occupancy/planner/**", received)
        replay = launch("replay", str(out / "bag"), "--ros2", "--ros2-router", endpoint,
                        "--speed", "0", "--wait-subscriber-s", "60")
        received.waiter.wait_for(lambda: len(received.samples) >= len(maps), 60,
                                 "the replayed maps on the ROS 2 key")
        assert replay.finish(60) == 0
        sub.undeclare()
    # The map travels as what changed; ROS 2 gets each step's whole map as a PointCloud2.
    wholes = Wholes()
    assert [p for _, p, _ in received.samples] == [
        shown for m in maps for shown in wholes.shown("planner_map", m)]
    assert [ros2.parse_attachment(a)[0] for _, _, a in received.samples] == [1, 2, 3]


def _one_point(i: int) -> np.ndarray:
    cloud = np.zeros(1, dtype=PLANNER_DTYPE)
    cloud["x"] = i
    return cloud


def test_a_holding_bridge_delivers_every_message_put_faster_than_it_sends():
    """A replay's bridge (``hold``) waits for room in its queue: three queues' worth of maps
    put at once all reach the ROS 2 subscriber, in order, none dropped (the live mission's
    bridge drops and counts instead, never holding up a step)."""
    n = 3 * ros2.QUEUE_MESSAGES
    endpoint = f"tcp/127.0.0.1:{free_loopback_port()}"
    router_conf, client_conf = _configs(endpoint)
    received = Received()
    with zenoh.open(router_conf), zenoh.open(client_conf) as ros:
        sub = ros.declare_subscriber("0/rover/map/occupancy/planner/**", received)
        bridge = ros2.Ros2Bridge(endpoint, hold=True)
        try:
            # (the replay's own wait: it polls the match, as Zenoh sends no event to a Waiter)
            _await_subscriber([], [bridge.watched], 30, threading.Event())
            token = _planner_publisher_token(ros)
            for i in range(n):  # keyframes: each is shown as it is, whole
                bridge.put("planner_map", encode("planner_map", (i, _one_point(i))), 0)
        finally:
            bridge.close()
        received.waiter.wait_for(lambda: len(received.samples) >= n, 60,
                                 f"the {n} maps on the ROS 2 key")
        sub.undeclare()
    assert bridge.dropped == 0
    shown = [TYPESTORE.deserialize_cdr(p, "sensor_msgs/msg/PointCloud2")
             for _, p, _ in received.samples]
    assert [m.header.stamp.sec for m in shown] == list(range(n))
    assert [m.width for m in shown] == [1] * n
    attachments = [ros2.parse_attachment(a) for _, _, a in received.samples]
    assert [seq for seq, _, _ in attachments] == list(range(1, n + 1))
    # Every sample carries the GID rmw_zenoh gives the publisher of that token.
    assert {gid for _, _, gid in attachments} == {_rmw_zenoh_gid(token)}


def test_without_a_router_the_bridge_does_not_start():
    """`run --ros2` opens the bridge before anything else starts; with no router at the
    endpoint it is one line (the command line prints it and exits with 2)."""
    from rovergate.errors import ConfigError
    port = free_loopback_port()  # nothing listens there
    with pytest.raises(ConfigError, match="no ROS 2 Zenoh router at") as err:
        ros2.Ros2Bridge(f"tcp/127.0.0.1:{port}", timeout_s=1.0)
    assert "\n" not in str(err.value)
