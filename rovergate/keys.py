"""Every key expression of the system, defined once.

All keys live under a namespace (default ``rover``). A topic pairs a key with the ROS 2 message
type that travels on it; the Zenoh encoding of every sample is ``application/cdr`` with the
type name as its schema, so a subscriber can check what it receives.
"""

from __future__ import annotations

from dataclasses import dataclass

#: Modules started by ``rovergate run``, in launch order.
MODULES: tuple[str, ...] = ("sim", "mapper", "gate", "planner")

#: The output each module publishes last in a step: once the mission has it for step t, the
#: module has handled step t. A restarted module resumes at that step (see mission/health.py).
PROGRESS_TOPIC: dict[str, str] = {"sim": "base_pose", "mapper": "predicted",
                                  "gate": "planner_map", "planner": "path"}


@dataclass(frozen=True)
class Topic:
    """A key (relative to the namespace) and the ROS 2 message type carried on it."""

    suffix: str
    msgtype: str
    doc: str
    network: str = "rover"
    """rover (the rover's processes) or ground (the ground station and the mission's bridge,
    under the ground namespace)."""


#: The public contract: the README's topic table is generated from the same entries.
TOPICS: dict[str, Topic] = {
    "depth": Topic("sensor/depth", "sensor_msgs/msg/Image",
                   "depth in metres (32FC1), NaN where there is no return"),
    "camera_info": Topic("sensor/camera_info", "sensor_msgs/msg/CameraInfo",
                         "intrinsics of the depth camera"),
    "pose": Topic("sensor/pose", "geometry_msgs/msg/PoseStamped",
                  "camera (optical frame: x right, y down, z forward) pose in frame `map`"),
    "base_pose": Topic("sensor/base_pose", "geometry_msgs/msg/PoseStamped",
                       "rover base (x forward, y left, z up) pose in frame `map`"),
    "surface": Topic("map/surface", "sensor_msgs/msg/PointCloud2",
                     "accumulated observed surface S_t: float32 x, y, z; uint16 views"),
    "predicted": Topic("map/occupancy/predicted", "sensor_msgs/msg/PointCloud2",
                       "learned prediction: float32 x, y, z, probability"),
    "planner_map": Topic("map/occupancy/planner", "sensor_msgs/msg/PointCloud2",
                         "planner-facing occupancy: float32 x, y, z; uint8 source; uint16 views"),
    "path": Topic("plan/path", "nav_msgs/msg/Path",
                  "rover base poses of the motion chosen for the next step"),
    "execution": Topic("state/execution", "rovergate_msgs/msg/ExecutionReport",
                       "what the simulator executed: collisions, clearance, length"),
    "status": Topic("mission/status", "rovergate_msgs/msg/MissionStatus",
                    "mission clock: step, coverage, state (the simulator's tick)"),
    "timing": Topic("diag/timing", "rovergate_msgs/msg/StepTiming",
                    "per-module compute time and dropped-message count per step"),
    "truth_surface": Topic("truth/surface_samples", "sensor_msgs/msg/PointCloud2",
                           "queryable: ground-truth surface samples (evaluation only)"),
    "truth_occupancy": Topic("truth/occupancy", "sensor_msgs/msg/PointCloud2",
                             "queryable: reference occupied points O* (oracle conditions only)"),
    "downlink": Topic("downlink", "rovergate_msgs/msg/TelemetryFrame",
                      "telemetry radiated in contact windows: status, pose, events, maps",
                      "ground"),
    "downlink_ack": Topic("downlink/ack", "rovergate_msgs/msg/DownlinkAck",
                          "the ground station's acknowledgement of sequence numbers", "ground"),
    "uplink": Topic("uplink", "rovergate_msgs/msg/GroundCommand",
                    "commands from the ground station (pause, resume, abort, set, ...)",
                    "ground"),
}


@dataclass(frozen=True)
class Keys:
    """Resolves topics and liveliness tokens under one namespace."""

    namespace: str = "rover"

    def key(self, topic: str) -> str:
        """Full key expression of a topic name from :data:`TOPICS`."""
        return f"{self.namespace}/{TOPICS[topic].suffix}"

    def alive(self, module: str) -> str:
        """Liveliness token a module declares once it is ready."""
        return f"{self.namespace}/alive/{module}"

    @property
    def alive_all(self) -> str:
        return f"{self.namespace}/alive/*"

    def journal(self, topic: str) -> str:
        """Queryable of the mission's journal of a topic: the samples of past steps, which a
        restarted module replays (parameters ``from`` and ``to``, steps inclusive)."""
        return f"{self.namespace}/mission/journal/{TOPICS[topic].suffix}"
