"""Every message type: one round-trip table, malformed bytes included."""

from __future__ import annotations

import numpy as np
import pytest

from rovergate.graph import TOPICS
from rovergate.messages import TYPESTORE, MessageError, decode, decode_item, encode, encode_item
from rovergate.streams import INCREMENTAL, StreamDecoder
from rovergate.types import (
    PLANNER_DTYPE,
    PREDICTED_DTYPE,
    SURFACE_DTYPE,
    XYZ_DTYPE,
    CameraIntrinsics,
    CommandAck,
    DownlinkAck,
    ExecutionReport,
    GroundCommand,
    MissionEvent,
    MissionStatus,
    PlannerMap,
    PlanPath,
    Pose,
    PoseWithCovariance,
    StepTiming,
    TelemetryFrame,
    TraversabilityGrid,
    TraverseReport,
)

rng = np.random.default_rng(0)


def _cloud(dtype, n=50):
    c = np.zeros(n, dtype=dtype)
    for name in dtype.names:
        c[name] = (rng.uniform(-5, 5, n) if dtype[name].kind == "f"
                   else rng.integers(0, 4, n)).astype(dtype[name])
    return c


depth = rng.uniform(0.5, 20, (12, 16)).astype(np.float32)
depth[3, 4] = np.nan
pose = Pose(np.array([1.5, -2.25, 0.3]), np.array([0.1, -0.2, 0.3, 0.9273618495495704]))
VALUES = {
    "depth": (7, depth),
    "camera_info": (7, CameraIntrinsics.from_fov(16, 12, 45.0)),
    "pose": (7, pose),
    "pose_cov": (7, PoseWithCovariance(pose, np.diag([0.04, 0.04, 0.01, 0.0, 0.0, 0.003]))),
    "base_pose": (7, Pose.from_xyz_yaw(1.0, 2.0, 0.5, 0.7)),
    "surface": (7, _cloud(SURFACE_DTYPE)),
    "predicted": (7, _cloud(PREDICTED_DTYPE)),
    "planner_map": PlannerMap(7, _cloud(PLANNER_DTYPE)),
    "path": PlanPath(7, [pose, Pose.from_xyz_yaw(2.0, 1.0, 0.0, -1.0)]),
    "rejected": PlanPath(7, []),
    "execution": ExecutionReport(7, True, 3, -0.01, 2.5, 0.8, contact=(1.0, -2.0, 0.5)),
    "hazcam_front": (7, depth),
    "hazcam_rear": (7, np.zeros((0, 0), dtype=np.float32)),  # a platform without them
    "hazcam_front_info": (7, CameraIntrinsics.from_fov(16, 12, 90.0)),
    "hazcam_rear_info": (7, CameraIntrinsics.from_fov(16, 12, 90.0)),
    "traverse": TraverseReport(7, {"unknown": 3, "wheel-drop": 1, "tilt": 0, "belly": 2},
                               "backout", 1234, np.array([0, 5, 70_000], np.uint32)),
    "traversability": TraversabilityGrid(7, np.array([[-1, 0], [100, 0], [0, -1]], np.int8),
                                         0.125, (-3.5, 2.25)),
    "status": MissionStatus(7, 100, "running", "obs", 0.25, 1),
    "timing": StepTiming(7, "plan", 0.125, 2),
    "truth_surface": (0, _cloud(XYZ_DTYPE)),
    "truth_occupancy": (0, _cloud(XYZ_DTYPE)),
    "downlink": TelemetryFrame(12, "status", "rovergate_msgs/msg/MissionStatus", 7, 420.0,
                               b"\x00\x01\x00\x00abc"),
    "downlink_ack": DownlinkAck([3, 4, 9]),
    "uplink": GroundCommand(5, "set", ["gate.k=3", "gate.epsilon_frac=0.05"]),
    "uplink_report": CommandAck(5, "set", "radiated", 7, 480.0, ""),
}
#: Topics whose step is 0 on the wire (queryables and the ground link's acks and commands).
STEP_ZERO = ("truth_surface", "truth_occupancy", "downlink_ack", "uplink")
ITEMS = {
    "status": MissionStatus(7, 100, "running", "obs", 0.25, 1),
    "pose": (7, pose),
    "map": (7, _cloud(SURFACE_DTYPE)),
    "event": MissionEvent(7, "module-restarted", "planner exited with code -9"),
    "command_ack": CommandAck(5, "pause", "executed", 7, 420.0, "paused at step 7"),
}


def _equal(a, b):
    if isinstance(a, np.ndarray):
        return a.dtype == b.dtype and np.array_equal(a, b, equal_nan=a.dtype.kind == "f")
    if hasattr(a, "__dataclass_fields__"):
        return all(_equal(getattr(a, f), getattr(b, f)) for f in a.__dataclass_fields__)
    if isinstance(a, list | tuple):
        return len(a) == len(b) and all(_equal(x, y) for x, y in zip(a, b, strict=True))
    return a == b


def test_every_topic_is_in_the_table():
    assert set(VALUES) == set(TOPICS)


def test_an_execution_without_contact_round_trips_to_none():
    clear = ExecutionReport(7, False, 0, 0.5, 2.5, 1.0)
    assert decode("execution", encode("execution", clear)) == (7, clear)


@pytest.mark.parametrize("topic", sorted(VALUES))
def test_round_trip_is_exact(topic):
    value = VALUES[topic]
    step, back = decode(topic, encode(topic, value))
    assert step == (0 if topic in STEP_ZERO else 7)
    if topic in INCREMENTAL:  # a whole value goes as a keyframe (rovergate.streams)
        assert back.keyframe
        back = StreamDecoder(topic).apply(back)
    expected = value[1] if isinstance(value, tuple) else value
    assert _equal(expected, back)


@pytest.mark.parametrize("topic", sorted(VALUES))
def test_wire_is_plain_ros2_cdr(topic):
    """Anyone with rosbags (or ROS 2) reads the wire as the documented type."""
    msg = TYPESTORE.deserialize_cdr(encode(topic, VALUES[topic]), TOPICS[topic].msgtype)
    assert msg.header.stamp.sec in (0, 7) and msg.header.stamp.nanosec == 0


@pytest.mark.parametrize("topic", sorted(VALUES))
@pytest.mark.parametrize("payload", [b"", b"\x00\x01\x00\x00", b"\x00\x01\x00\x00garbage!",
                                     bytes(range(256))])
def test_malformed_bytes_raise_message_error(topic, payload):
    with pytest.raises(MessageError):
        decode(topic, payload)


@pytest.mark.parametrize("topic", sorted(VALUES))
def test_truncated_message_raises_message_error(topic):
    data = encode(topic, VALUES[topic])
    with pytest.raises(MessageError):
        decode(topic, data[: len(data) // 2])


@pytest.mark.parametrize("kind", sorted(ITEMS))
def test_telemetry_items_round_trip_and_refuse_garbage(kind):
    msgtype, payload = encode_item(kind, ITEMS[kind])
    expected = ITEMS[kind][1] if isinstance(ITEMS[kind], tuple) else ITEMS[kind]
    assert _equal(expected, decode_item(kind, msgtype, payload))
    with pytest.raises(MessageError):
        decode_item(kind, msgtype, payload[: len(payload) // 2])
    with pytest.raises(MessageError, match="not one this version knows"):
        decode_item(kind, "std_msgs/msg/String", payload)


def test_wrong_shape_is_refused():
    # A cloud without the fields the topic needs.
    with pytest.raises(MessageError, match="lacks field 'source'"):
        decode("planner_map", encode("planner_map", (1, _cloud(XYZ_DTYPE))))
    # A depth image whose data does not fill its size.
    msg = TYPESTORE.deserialize_cdr(encode("depth", VALUES["depth"]), "sensor_msgs/msg/Image")
    msg.width = 99
    with pytest.raises(MessageError, match="carries"):
        decode("depth", bytes(TYPESTORE.serialize_cdr(msg, "sensor_msgs/msg/Image")))
    # A pose whose quaternion is not a rotation.
    bad = Pose(np.zeros(3), np.array([0.0, 0.0, 0.0, 2.0]))
    with pytest.raises(MessageError, match="norm"):
        decode("pose", encode("pose", (1, bad)))
