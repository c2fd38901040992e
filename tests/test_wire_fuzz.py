"""The wire under attack (property tests, no network): whatever bytes arrive on a topic,
a reader either gets a valid value or a :class:`MessageError`, never another exception, a
crash or an allocation its sender chose; the same for telemetry items on the ground."""

from __future__ import annotations

import contextlib

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from test_messages import ITEMS, VALUES

from rovergate.graph import TOPICS
from rovergate.messages import (
    MAX_IMAGE_PIXELS,
    MAX_PATH_POSES,
    MAX_POINTS,
    TYPESTORE,
    MessageError,
    decode,
    decode_item,
    encode,
    encode_item,
)

FUZZ = settings(max_examples=150, deadline=None, derandomize=True,
                suppress_health_check=[HealthCheck.too_slow])
WIRE = {topic: encode(topic, value) for topic, value in VALUES.items()}


def _decodes_or_refuses(topic: str, payload: bytes) -> None:
    with contextlib.suppress(MessageError):
        decode(topic, payload)


@pytest.mark.parametrize("topic", sorted(WIRE))
@FUZZ
@given(data=st.binary(max_size=512))
def test_random_bytes_are_refused_or_decoded_never_raised(topic, data):
    _decodes_or_refuses(topic, data)


@pytest.mark.parametrize("topic", sorted(WIRE))
@FUZZ
@given(data=st.data())
def test_mutated_cdr_is_refused_or_decoded_never_raised(topic, data):
    """A valid message with bytes flipped, cut or added: the header, a sequence length, a
    field's offset or datatype, a float's bits (NaN, infinities) change under it."""
    wire = bytearray(WIRE[topic])
    for _ in range(data.draw(st.integers(1, 8))):
        i = data.draw(st.integers(0, len(wire) - 1))
        wire[i] = data.draw(st.integers(0, 255))
    cut = data.draw(st.integers(0, len(wire)))
    tail = data.draw(st.binary(max_size=16))
    _decodes_or_refuses(topic, bytes(wire[:cut]) + tail)


@pytest.mark.parametrize("kind", sorted(ITEMS))
@FUZZ
@given(data=st.data())
def test_mutated_telemetry_items_are_refused_or_decoded(kind, data):
    msgtype, payload = encode_item(kind, ITEMS[kind])
    wire = bytearray(payload)
    for _ in range(data.draw(st.integers(1, 6))):
        i = data.draw(st.integers(0, len(wire) - 1))
        wire[i] = data.draw(st.integers(0, 255))
    with contextlib.suppress(MessageError):
        decode_item(kind, msgtype, bytes(wire[:data.draw(st.integers(0, len(wire)))]))


def _forged(msgtype: str, msg) -> bytes:
    return bytes(TYPESTORE.serialize_cdr(msg, msgtype))


@FUZZ
@given(width=st.integers(MAX_POINTS + 1, 2**32 - 1))
def test_a_cloud_declaring_too_many_points_is_refused_before_allocation(width):
    msg = TYPESTORE.deserialize_cdr(WIRE["surface"], TOPICS["surface"].msgtype)
    # The data stays a few hundred bytes; only the declared size grows: of the points the
    # message carries, or of the cloud an update says it makes.
    points = msg.points
    points.width, points.row_step = width, (width * points.point_step) % 2**32
    with pytest.raises(MessageError, match="over the limit of"):
        decode("surface", _forged(TOPICS["surface"].msgtype, msg))
    msg = TYPESTORE.deserialize_cdr(WIRE["surface"], TOPICS["surface"].msgtype)
    msg.size = width
    with pytest.raises(MessageError, match="over the limit of"):
        decode("surface", _forged(TOPICS["surface"].msgtype, msg))


@FUZZ
@given(w=st.integers(1, 2**31 - 1), h=st.integers(1, 2**31 - 1))
def test_a_depth_image_is_never_larger_than_its_limit(w, h):
    msg = TYPESTORE.deserialize_cdr(WIRE["depth"], TOPICS["depth"].msgtype)
    msg.width, msg.height, msg.step = w, h, (4 * w) % 2**32
    with pytest.raises(MessageError,
                       match="over the limit" if w * h > MAX_IMAGE_PIXELS else "carries"):
        decode("depth", _forged(TOPICS["depth"].msgtype, msg))


def test_a_path_of_too_many_poses_is_refused():
    msg = TYPESTORE.deserialize_cdr(WIRE["path"], TOPICS["path"].msgtype)
    msg.poses = [msg.poses[0]] * (MAX_PATH_POSES + 1)
    with pytest.raises(MessageError, match="over the limit of 10000"):
        decode("path", _forged(TOPICS["path"].msgtype, msg))


@pytest.mark.parametrize("value", [float("nan"), float("inf"), -float("inf")])
def test_non_finite_poses_and_intrinsics_are_refused(value):
    msg = TYPESTORE.deserialize_cdr(WIRE["path"], TOPICS["path"].msgtype)
    msg.poses[1].pose.position.x = value
    with pytest.raises(MessageError, match="non-finite"):
        decode("path", _forged(TOPICS["path"].msgtype, msg))
    info = TYPESTORE.deserialize_cdr(WIRE["camera_info"], TOPICS["camera_info"].msgtype)
    info.k = np.array([value, 0, 8, 0, 10, 6, 0, 0, 1], dtype=np.float64)
    with pytest.raises(MessageError, match="intrinsics"):
        decode("camera_info", _forged(TOPICS["camera_info"].msgtype, info))
