"""The live view (issue 17, part 2): a Foxglove WebSocket server that a client written from
the Foxglove WebSocket protocol alone (JSON control messages, binary message data) connects
to, subscribes to the planner map's channel on, and decodes with a ROS 2 decoder that reads
the schema the server advertises."""

from __future__ import annotations

import json
import struct
import time
from pathlib import Path

import numpy as np
import pytest
from mcap.records import Schema
from mcap_ros2.decoder import DecoderFactory
from websockets.exceptions import InvalidStatus
from websockets.sync.client import ClientConnection, connect

from tests.conftest import recorded_mission

SUBPROTOCOL = "foxglove.sdk.v1"
OLD_SUBPROTOCOL = "foxglove.websocket.v1"
"""The same protocol's earlier name, all that older clients offer."""
MESSAGE_DATA = 0x01
PLANNER = "/rover/map/occupancy/planner"


class FoxgloveClient:
    """The protocol's client side: serverInfo and advertise come as JSON text; a subscribe
    names channel ids; each message comes as binary opcode 0x01, uint32 subscription id,
    uint64 log time (little-endian), then the payload."""

    def __init__(self, url: str, subprotocols: tuple[str, ...] = (SUBPROTOCOL,)) -> None:
        # The server listens before the mission logs its address, which the test awaited.
        self.ws: ClientConnection = connect(url, subprotocols=list(subprotocols),
                                            max_size=None, open_timeout=30)
        self.info: dict = {}
        self.channels: dict[int, dict] = {}
        self._subs: dict[int, int] = {}

    def __enter__(self) -> FoxgloveClient:
        self.ws.__enter__()
        return self

    def __exit__(self, *exc) -> None:
        self.ws.__exit__(*exc)

    def read_until(self, done, timeout_s: float, what: str):
        deadline = time.monotonic() + timeout_s
        while (result := done()) is None:
            left = deadline - time.monotonic()
            if left <= 0:
                raise AssertionError(f"no {what} from the live view within {timeout_s:.0f} s")
            try:
                frame = self.ws.recv(timeout=left)
            except TimeoutError:
                continue
            if isinstance(frame, str):
                msg = json.loads(frame)
                if msg["op"] == "serverInfo":
                    self.info = msg
                elif msg["op"] == "advertise":
                    self.channels.update({c["id"]: c for c in msg["channels"]})
            elif frame[0] == MESSAGE_DATA:
                sub, log_time = struct.unpack_from("<IQ", frame, 1)
                self.received.append((self._subs[sub], log_time, frame[13:]))
        return result

    def channel(self, topic: str) -> dict | None:
        return next((c for c in self.channels.values() if c["topic"] == topic), None)

    def subscribe(self, topics: list[str]) -> None:
        self.received: list[tuple[int, int, bytes]] = []
        subs = []
        for topic in topics:
            cid = self.channel(topic)["id"]
            sub = len(self._subs) + 1
            self._subs[sub] = cid
            subs.append({"id": sub, "channelId": cid})
        self.ws.send(json.dumps({"op": "subscribe", "subscriptions": subs}))

    def first(self, topic: str):
        cid = self.channel(topic)["id"]
        return next((payload for c, _, payload in self.received if c == cid), None)


def _decode(channel: dict, payload: bytes):
    schema = Schema(id=channel["id"], name=channel["schemaName"],
                    encoding=channel["schemaEncoding"], data=channel["schema"].encode())
    return DecoderFactory().decoder_for(channel["encoding"], schema)(payload)


@pytest.mark.e2e
@pytest.mark.parametrize("mode", ["processes", "in-process"])
def test_a_foxglove_client_subscribes_to_the_planner_map_and_decodes_it(
        launch, tmp_path: Path, mode: str):
    # In process, the clouds reach the view unencoded (rovergate.taps.Deferred).
    extra = ["--in-process"] if mode == "in-process" else []
    mission = launch("run", "--viz", "--viz-port", "0", "--steps", "400", "--platform",
                     "flyer", "--out", str(tmp_path / "run"), *extra)
    port = int(mission.wait_for_line(r"live view: open ws://127\.0\.0\.1:(\d+)").group(1))
    with FoxgloveClient(f"ws://127.0.0.1:{port}") as client:
        client.read_until(lambda: client.channel(PLANNER) and client.channel("/tf")
                          and client.info or None, 60, "serverInfo and channels")
        # Watch only: the server grants no capability (no client publishing, services,
        # parameters), so nothing a viewer sends can reach the mission.
        assert client.info["capabilities"] == []
        planner = client.channel(PLANNER)
        assert (planner["encoding"], planner["schemaEncoding"], planner["schemaName"]) == (
            "cdr", "ros2msg", "sensor_msgs/msg/PointCloud2")
        client.subscribe([PLANNER, "/tf", "/rover/scene"])
        client.read_until(lambda: client.first(PLANNER) and client.first("/tf")
                          and client.first("/rover/scene") or None, 120,
                          "planner map, transform and scene")
        cloud = _decode(planner, client.first(PLANNER))
        assert cloud.header.frame_id == "map"
        names = [f.name for f in cloud.fields]
        assert names == ["x", "y", "z", "source", "views", "channels"]
        n = cloud.width * cloud.height
        assert n > 0 and len(cloud.data) == n * cloud.point_step
        source = np.frombuffer(bytes(cloud.data), np.uint8).reshape(n, cloud.point_step)[
            :, cloud.fields[3].offset]
        assert set(np.unique(source)) <= {0, 1, 2, 3}
        tf = _decode(client.channel("/tf"), client.first("/tf"))
        assert tf.transforms[0].header.frame_id == "map"
        assert tf.transforms[0].child_frame_id in ("camera", "base_link")
        assert len(client.first("/rover/scene")) > 10_000  # the scene's triangles
    mission.kill()


def test_the_live_view_answers_only_clients_that_offer_the_sdk_subprotocol():
    """foxglove-sdk 0.30.3 accepts a client only if it offers ``foxglove.sdk.v1``: its handshake
    compares with one constant (``rust/foxglove/src/websocket/handshake.rs``) and
    ``start_server`` has no option for another. A client offering only
    ``foxglove.websocket.v1`` (the @foxglove/ws-protocol client's default, older Foxglove
    apps, Lichtblick before 1.22) gets HTTP 400 and no serverInfo; one offering both names, in
    Lichtblick's order, is answered in ``foxglove.sdk.v1`` (the same protocol renamed)."""
    from ecosystem.live_view import LiveView
    view = LiveView(port=0)
    url = f"ws://127.0.0.1:{view.port}"
    try:
        with pytest.raises(InvalidStatus) as refused:
            connect(url, subprotocols=[OLD_SUBPROTOCOL], open_timeout=10)
        response = refused.value.response
        assert response.status_code == 400
        assert bytes(response.body) == b"Missing expected sec-websocket-protocol header"
        with FoxgloveClient(url, (OLD_SUBPROTOCOL, SUBPROTOCOL)) as client:
            assert client.ws.subprotocol == SUBPROTOCOL
            client.read_until(lambda: client.info and client.channel(PLANNER) or None, 30,
                              "serverInfo and the planner map's channel")
        assert client.info["capabilities"] == []
    finally:
        view.close()


def test_the_committed_layout_is_the_generated_one():
    from ecosystem.layout import layout_json
    committed = (Path(__file__).resolve().parents[1] / "docs" / "foxglove-layout.json")
    assert committed.read_text() == layout_json(), \
        "docs/foxglove-layout.json is stale: python -m ecosystem.layout > docs/foxglove-layout.json"
    panels = json.loads(committed.read_text())["content"]["items"][0]["content"]
    planner = panels["config"]["topics"][PLANNER]
    assert (planner["colorMode"], planner["colorField"]) == ("colormap", "source")


@pytest.mark.e2e
def test_replay_serves_a_recorded_mission_to_foxglove(launch, tmp_path: Path):
    out = tmp_path / "run"
    recorded_mission(out, 2)
    replay = launch("replay", str(out / "bag"), "--viz", "--viz-port", "0", "--listen",
                    "--speed", "0", "--wait-subscriber-s", "120", "--topics", PLANNER)
    port = int(replay.wait_for_line(r"live view: open ws://127\.0\.0\.1:(\d+)").group(1))
    with FoxgloveClient(f"ws://127.0.0.1:{port}") as client:
        client.read_until(lambda: client.channel(PLANNER), 60, "the planner map's channel")
        client.subscribe([PLANNER, "/rover/scene"])
        client.read_until(lambda: client.first("/rover/scene") and client.first(PLANNER), 60,
                          "the scene (from the config.json beside the bag) and a map")
        cloud = _decode(client.channel(PLANNER), client.first(PLANNER))
        assert cloud.header.stamp.sec == 0  # the replay starts at the recording's start
    # The README's picture of the layout is drawn from such a bag.
    from ecosystem.layout import picture
    picture(out / "bag", tmp_path / "layout.png")
    assert (tmp_path / "layout.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
