"""The ROS 2 graph over rmw_zenoh: the mission's topics as ROS 2 Jazzy (and later) nodes that
run ``rmw_zenoh_cpp`` see them, without a ROS installation here.

``rovergate run --ros2`` (and ``rovergate replay --ros2``) joins the ROS 2 Zenoh router
(``rmw_zenohd``, by default on ``tcp/localhost:7447``, ``--ros2-router``) as a Zenoh client and
publishes every topic of the rover's network as rmw_zenoh does (its ``docs/design.md``, the
version with the 33-byte attachment: Jazzy 0.2.4 and later, Rolling 0.6 and later):

- **data keys** ``<domain>/<topic without its leading slash>/<type in DDS form>/<RIHS01
  hash>``, e.g. ``0/rover/map/occupancy/planner/sensor_msgs::msg::dds_::PointCloud2_/
  RIHS01_9198…``; the hash is the type description hash rosbags computes from the message
  definition (``std_msgs/msg/String`` gives the design document's
  ``RIHS01_df668c74…``);
- **payloads**: the CDR bytes as the mission sent them (the same 4-byte encapsulation header
  rmw_zenoh writes), but the incremental maps (the surface, the prediction, the planner map),
  which are made whole again and published as ``sensor_msgs/msg/PointCloud2``
  (:class:`rovergate.streams.Wholes`: from the first keyframe the bridge sees);
- **an attachment on every sample**: int64 sequence number (from 1, per publisher), int64 source
  timestamp (ns since the epoch), the GID's length (one byte, 16) and the 16-byte publisher
  GID, little-endian: 33 bytes;
- **liveliness tokens** for one node, ``/<namespace>/rovergate_bridge``, and one publisher per
  topic: ``@ros2_lv/<domain>/<session zid>/<node id>/<entity id>/<NN|MP>/<enclave>/
  <namespace>/<node>[/<topic>/<type>/<hash>/<qos>]``, ``/`` written ``%``; QoS reliable,
  volatile, keep last 10 (``::,10:,:,:,,``), so ``ros2 topic list`` shows the topics and
  ``ros2 topic echo /rover/map/occupancy/planner`` prints the map.

The other way is closed: the bridge declares no subscriber, queryable or token a ROS 2 node
could reach the mission through. A ROS 2 node's command (a ``nav_msgs/msg/Path`` from a ROS 2
planner) does not reach the rover by this path at all; commands go up only through the ground
link's authenticated, allowlisted uplink (``rovergate ground``; docs/security.md).

A publisher's GID is rmw_zenoh's: the XXH3-128 hash of its liveliness token (:func:`gid_of`),
so that a ROS 2 tool that matches a sample's GID against the graph's publishers finds ours.

rovergate's own types (``rovergate_msgs/msg/...``) decode on the ROS 2 side once the interface
package ``ros2/rovergate_msgs`` (copies of ``rovergate/msg/``) is built in its workspace.
"""

from __future__ import annotations

import json
import logging
import queue
import struct
import threading
import time

import xxhash

from rovergate.errors import ConfigError
from rovergate.keys import Keys
from rovergate.messages import TYPESTORE
from rovergate.streams import Wholes, shown_type
from rovergate.taps import tapped_topics

log = logging.getLogger("rovergate.ros2")

DEFAULT_ROUTER = "tcp/localhost:7447"
NODE_NAME = "rovergate_bridge"
#: rmw_zenoh's QoS in a token, each field left empty where it is rmw_zenoh's default
#: (reliable, volatile, keep last; depth 10 given): what rclcpp's QoS(10) publisher shows.
QOS_KEEP_LAST_10 = "::,10:,:,:,,"
GID_BYTES = 16
#: Messages waiting for the router, at most (about 17 steps of every topic); past it, a
#: message is dropped and counted rather than the mission held up.
QUEUE_MESSAGES = 256


def dds_type(msgtype: str) -> str:
    """``sensor_msgs/msg/PointCloud2`` -> ``sensor_msgs::msg::dds_::PointCloud2_``."""
    package, kind, name = msgtype.split("/")
    return f"{package}::{kind}::dds_::{name}_"


def type_hash(msgtype: str) -> str:
    """The RIHS01 type description hash (``RIHS01_`` and 64 hex digits)."""
    return TYPESTORE.hash_rihs01(msgtype)


def data_key(domain: int, topic: str, msgtype: str) -> str:
    """The key rmw_zenoh publishes a topic's samples on."""
    return f"{domain}/{topic.strip('/')}/{dds_type(msgtype)}/{type_hash(msgtype)}"


def mangle(name: str) -> str:
    """A name in a liveliness token: every ``/`` as ``%`` (an empty name or ``/`` is ``%``)."""
    return name.replace("/", "%") if name else "%"


def node_token(domain: int, zid: str, node_id: int, namespace: str, node: str,
               enclave: str = "/") -> str:
    return (f"@ros2_lv/{domain}/{zid}/{node_id}/{node_id}/NN/{mangle(enclave)}/"
            f"{mangle(namespace)}/{node}")


def publisher_token(domain: int, zid: str, node_id: int, entity_id: int, namespace: str,
                    node: str, topic: str, msgtype: str, qos: str = QOS_KEEP_LAST_10,
                    enclave: str = "/") -> str:
    return (f"@ros2_lv/{domain}/{zid}/{node_id}/{entity_id}/MP/{mangle(enclave)}/"
            f"{mangle(namespace)}/{node}/{mangle(topic)}/{dds_type(msgtype)}/"
            f"{type_hash(msgtype)}/{qos}")


def attachment(sequence: int, timestamp_ns: int, gid: bytes) -> bytes:
    """The 33 bytes every rmw_zenoh sample carries (module docstring)."""
    if len(gid) != GID_BYTES:
        raise ValueError(f"a publisher GID has {GID_BYTES} bytes, got {len(gid)}")
    return struct.pack("<qqB", sequence, timestamp_ns, GID_BYTES) + gid


def parse_attachment(data: bytes) -> tuple[int, int, bytes]:
    """(sequence number, source timestamp ns, GID) of an attachment; ValueError if it is not
    one."""
    if len(data) != 8 + 8 + 1 + GID_BYTES or data[16] != GID_BYTES:
        raise ValueError(f"not an rmw_zenoh attachment ({len(data)} bytes)")
    seq, ts = struct.unpack_from("<qq", data)
    return seq, ts, bytes(data[17:])


def gid_of(token: str) -> bytes:
    """The 16-byte GID rmw_zenoh gives the entity whose liveliness token is ``token``.

    rmw_zenoh (``liveliness_utils.cpp``, ``Entity::Entity``) hashes the token's characters with
    XXH3-128 (seed 0, the default secret) into a ``{uint64 low64; uint64 high64}`` and copies
    the two words into the GID with ``memcpy``: ``low64`` into bytes 0-7, ``high64`` into
    bytes 8-15, each in the machine's byte order, which is little-endian on every platform
    ROS 2 supports. So the GID is the 128-bit hash written little-endian, its lowest byte
    first: ``XXH128_canonical``'s (big-endian, ``xxhash``'s ``hexdigest()``) 16 bytes
    reversed. The token ``""`` (hash ``99aa06d3014798d8_6001c324468d497f``) gives
    ``7f498d4624c30160_d8984701d306aa99``."""
    return xxhash.xxh3_128_intdigest(token.encode()).to_bytes(GID_BYTES, "little")


class Ros2Bridge:
    """A :class:`rovergate.taps.Tap` that publishes the mission into the ROS 2 graph."""

    def __init__(self, router: str = DEFAULT_ROUTER, domain: int = 0,
                 namespace: str = "rover", timeout_s: float = 5.0,
                 hold: bool = False) -> None:
        """``hold``: :meth:`put` waits for room in the queue instead of dropping (a replay,
        whose pace is its own: every message of the bag reaches ROS 2, as ``ros2 bag play``
        delivers them); a live mission never waits on the router."""
        import zenoh
        if not 0 <= domain <= 232:
            raise ConfigError(f"--ros2-domain must be a ROS domain id (0 to 232), got {domain}")
        conf = zenoh.Config()
        conf.insert_json5("mode", '"client"')
        conf.insert_json5("connect/endpoints", json.dumps([router]))
        conf.insert_json5("scouting/multicast/enabled", "false")
        conf.insert_json5("connect/timeout_ms", str(int(timeout_s * 1000)))
        # rmw_zenoh's sessions stamp their samples (its publication caches need it).
        conf.insert_json5("timestamping/enabled", '{"router": true, "peer": true, "client": true}')
        try:
            self.session = zenoh.open(conf)
        except Exception as exc:
            raise ConfigError(f"--ros2: no ROS 2 Zenoh router at {router} ({exc}); start one "
                              "(`ros2 run rmw_zenoh_cpp rmw_zenohd`) or give its endpoint with "
                              "--ros2-router") from None
        self.domain = domain
        self.zid = str(self.session.info.zid())
        self.node_namespace = f"/{namespace}"
        keys = Keys(namespace)
        liveliness = self.session.liveliness()
        self._tokens = [liveliness.declare_token(
            node_token(domain, self.zid, 0, self.node_namespace, NODE_NAME))]
        self._publishers: dict[str, tuple[zenoh.Publisher, bytes]] = {}
        self._sequence: dict[str, int] = {}
        self._queue: queue.Queue[tuple[str, bytes] | None] = queue.Queue(QUEUE_MESSAGES)
        self.dropped = 0
        self._hold = hold
        self._wholes = Wholes()
        for entity, topic in enumerate(tapped_topics(), start=1):
            name, msgtype = "/" + keys.key(topic), shown_type(topic)
            token = publisher_token(domain, self.zid, 0, entity, self.node_namespace,
                                    NODE_NAME, name, msgtype)
            self._publishers[topic] = (
                self.session.declare_publisher(
                    data_key(domain, name, msgtype),
                    congestion_control=zenoh.CongestionControl.BLOCK),
                gid_of(token))
            self._sequence[topic] = 0
            self._tokens.append(liveliness.declare_token(token))
        self._thread = threading.Thread(target=self._send, name="ros2-bridge", daemon=True)
        self._thread.start()
        log.info("ROS 2 graph: node %s/%s on domain %d via the router at %s (%d topics)",
                 self.node_namespace, NODE_NAME, domain, router, len(self._publishers))

    def put(self, topic: str, payload: bytes, time_ns: int) -> None:
        """Hand a message to the bridge's thread; never blocks the mission (a router that
        does not keep up costs ROS 2 messages, counted, never the mission a step), but
        waits for room with ``hold`` (a replay)."""
        if topic not in self._publishers:
            return
        while self._hold and self._thread.is_alive():  # (a bridge that stopped drops)
            try:
                self._queue.put((topic, payload), timeout=1.0)
                return
            except queue.Full:
                continue
        try:
            self._queue.put_nowait((topic, payload))
        except queue.Full:
            self.dropped += 1
            if self.dropped == 1 or self.dropped % 100 == 0:
                log.warning("the ROS 2 router does not keep up: %d messages not sent to ROS 2 "
                            "so far", self.dropped)

    def _send(self) -> None:
        while (item := self._queue.get()) is not None:
            topic, payload = item
            publisher, gid = self._publishers[topic]
            for data in self._wholes.shown(topic, bytes(payload)):  # maps made whole
                self._sequence[topic] += 1  # per publisher, from 1, in the order sent
                try:
                    publisher.put(data, attachment=attachment(self._sequence[topic],
                                                              time.time_ns(), gid))
                except Exception as exc:  # the session closed under us: stop sending
                    log.error("the ROS 2 bridge stopped: %s", exc)
                    return

    def watched(self) -> bool:
        """True once a ROS 2 subscriber matches one of the bridge's publishers."""
        return any(p.matching_status.matching for p, _ in self._publishers.values())

    def close(self) -> None:
        self._queue.put(None)  # after what is queued
        self._thread.join(30)
        if self.dropped:
            log.warning("%d messages were not sent to ROS 2 (the router did not keep up)",
                        self.dropped)
        for token in self._tokens:
            token.undeclare()
        for publisher, _ in self._publishers.values():
            publisher.undeclare()
        self.session.close()
