"""The live view: a Foxglove WebSocket server (``foxglove-sdk``) fed by the mission's taps.

``rovergate run --viz`` (and ``rovergate replay --viz``) starts it on ``ws://127.0.0.1:8765``
(``--viz-host``, ``--viz-port``; port 0 takes a free one, and the log says which). Open it in
Foxglove (Open connection, Foxglove WebSocket, that address) and import the layout
``docs/foxglove-layout.json``.

The server speaks the Foxglove WebSocket protocol under its current subprotocol name,
``foxglove.sdk.v1``, and only that: foxglove-sdk's handshake (0.30) compares the client's offer
with that one constant, and ``start_server`` has no option to add its earlier name,
``foxglove.websocket.v1``. The Foxglove app, Lichtblick 1.22 and later (which offer both) and
foxglove-sdk's own clients connect; a client offering only ``foxglove.websocket.v1`` (older
Foxglove Studio, Lichtblick before 1.22, the ``@foxglove/ws-protocol`` client unless given the
new name) gets HTTP 400 "Missing expected sec-websocket-protocol header". The protocol is the
same under both names, so such a client needs only to offer the new one.

Channels:

- every topic of the rover's network as it travels: its ROS 2 topic name
  (``/rover/map/occupancy/planner``), schema encoding ``ros2msg`` (the type's definition),
  message encoding ``cdr``, the bytes unchanged: depth image, intrinsics, poses, path,
  status; the surface, the prediction and the planner map (the layout colours it by its
  ``source`` field) whole, as ``sensor_msgs/msg/PointCloud2``, though they travel as what
  changed (:class:`rovergate.streams.Wholes`; a viewer sees them from the next keyframe);
- ``/tf``, a ``tf2_msgs/msg/TFMessage`` per pose: ``map`` to ``camera`` (the depth camera's
  optical frame, the frame of the image and intrinsics), ``map`` to ``base_link`` (the
  platform's base) and ``map`` to ``hazcam_front_optical`` and ``hazcam_rear_optical`` (the
  rover's hazard cameras, from the base pose and their mounting), stamped with the step as
  every message is;
- ``/rover/scene``, the scene's true mesh, once per subscriber, as a ``foxglove.SceneUpdate``
  (for orientation: the mission's maps are scored against it).

The server advertises no capability beyond subscribing: a client cannot publish, call a
service or set a parameter, so nothing a viewer sends reaches the mission.
"""

from __future__ import annotations

import logging
import threading
from typing import Protocol

import numpy as np

from rovergate.config import HazcamConfig
from rovergate.keys import Keys
from rovergate.messages import TYPESTORE
from rovergate.streams import Wholes, shown_type
from rovergate.taps import tapped_topics


class Scene(Protocol):
    """What the view needs of a scene (:class:`rover_sim.scene.Scene` is one; the mission
    hands it in, so this package imports no module package)."""

    visual_meshes: list
    """(trimesh.Trimesh, RGBA) pairs: the scene's true geometry in its own colours."""

log = logging.getLogger("rovergate.viz")

DEFAULT_PORT = 8765
#: The pose topics whose frames the view broadcasts on /tf: topic -> child frame.
FRAMES = {"pose": "camera", "base_pose": "base_link"}
TF_TOPIC = "/tf"
TF_TYPE = "tf2_msgs/msg/TFMessage"


def ros2msg_schema(msgtype: str):
    """A Foxglove schema of a ROS 2 type: its ``.msg`` definition with its dependencies."""
    import foxglove
    text, _ = TYPESTORE.generate_msgdef(msgtype, ros_version=2)
    return foxglove.Schema(name=msgtype, encoding="ros2msg", data=text.encode())


def scene_topic(namespace: str) -> str:
    return f"/{namespace}/scene"


class LiveView:
    """A :class:`rovergate.taps.Tap` that serves the mission to Foxglove."""

    def __init__(self, host: str = "127.0.0.1", port: int = DEFAULT_PORT,
                 namespace: str = "rover", scene: Scene | None = None,
                 name: str = "rovergate", hazcam: HazcamConfig | None = None) -> None:
        """``hazcam``: the hazard cameras' mounting, for their frames on /tf (the default
        mounting if None)."""
        self.hazcam = hazcam or HazcamConfig()
        try:
            import foxglove
            from foxglove.channels import SceneUpdateChannel
        except ImportError:
            from rovergate.errors import ConfigError
            raise ConfigError("--viz needs the foxglove-sdk package: pip install -e '.[viz]' "
                              "(`make test` installs it)") from None
        self._context = foxglove.Context()
        keys = Keys(namespace)
        self.channels = {
            t: foxglove.Channel("/" + keys.key(t), schema=ros2msg_schema(shown_type(t)),
                                message_encoding="cdr", context=self._context)
            for t in tapped_topics()}
        self._tf = foxglove.Channel(TF_TOPIC, schema=ros2msg_schema(TF_TYPE),
                                    message_encoding="cdr", context=self._context)
        self._scene_channel = SceneUpdateChannel(scene_topic(namespace), context=self._context)
        self._scene = _scene_update(scene) if scene is not None else None
        self._lock = threading.Lock()
        self._wholes = Wholes()
        self._watched = threading.Event()
        view = self

        class Listener(foxglove.ServerListener):
            def on_subscribe(self, client, channel) -> None:
                if channel.topic == scene_topic(namespace):
                    view.send_scene()
                else:
                    view._watched.set()

        try:
            self.server = foxglove.start_server(
                name=name, host=host, port=port, capabilities=[], server_listener=Listener(),
                context=self._context)
        except Exception as exc:
            from rovergate.errors import ConfigError
            raise ConfigError(f"cannot start the live view on {host}:{port} ({exc}); give "
                              "--viz-port another port (0: any free one)") from None
        self.port = self.server.port
        log.info("live view: open ws://%s:%d in Foxglove (layout: docs/foxglove-layout.json)",
                 host, self.port)

    def put(self, topic: str, payload: bytes, time_ns: int) -> None:
        channel = self.channels.get(topic)
        if channel is None:
            return
        data = bytes(payload)
        for shown in self._wholes.shown(topic, data):  # an incremental map: made whole
            channel.log(shown, log_time=time_ns)
        if topic in FRAMES:
            self._tf.log(_transform(data, FRAMES[topic]), log_time=time_ns)
        if topic == "base_pose":  # the hazard cameras ride on the base (their mounting)
            self._tf.log(_hazcam_transforms(data, self.hazcam), log_time=time_ns)

    def watched(self) -> bool:
        """True once a Foxglove client subscribed to a channel of the mission."""
        return self._watched.is_set()

    def send_scene(self) -> None:
        if self._scene is not None:
            with self._lock:
                self._scene_channel.log(self._scene)

    def close(self) -> None:
        self.server.stop()


def _transform(pose_stamped: bytes, child: str) -> bytes:
    """A TFMessage placing ``child`` at the pose of a PoseStamped (CDR in, CDR out)."""
    T = TYPESTORE.types
    msg = TYPESTORE.deserialize_cdr(pose_stamped, "geometry_msgs/msg/PoseStamped")
    p = msg.pose.position
    tf = T["geometry_msgs/msg/TransformStamped"](
        header=msg.header, child_frame_id=child,
        transform=T["geometry_msgs/msg/Transform"](
            translation=T["geometry_msgs/msg/Vector3"](x=p.x, y=p.y, z=p.z),
            rotation=msg.pose.orientation))
    return bytes(TYPESTORE.serialize_cdr(T[TF_TYPE](transforms=[tf]), TF_TYPE))


def _hazcam_transforms(base_pose_stamped: bytes, hazcam: HazcamConfig) -> bytes:
    """A TFMessage placing ``hazcam_front_optical`` and ``hazcam_rear_optical`` at the
    hazard cameras' poses for a base PoseStamped (CDR in, CDR out)."""
    from rovergate.geometry import HAZCAMS, hazcam_from_base, matrix_to_quat
    from rovergate.messages import pose_from_ros
    T = TYPESTORE.types
    msg = TYPESTORE.deserialize_cdr(base_pose_stamped, "geometry_msgs/msg/PoseStamped")
    base = pose_from_ros(msg)[1].matrix()
    out = []
    for name in HAZCAMS:
        M = hazcam_from_base(base, hazcam, name)
        q = matrix_to_quat(M[:3, :3])
        out.append(T["geometry_msgs/msg/TransformStamped"](
            header=msg.header, child_frame_id=f"hazcam_{name}_optical",
            transform=T["geometry_msgs/msg/Transform"](
                translation=T["geometry_msgs/msg/Vector3"](*(float(v) for v in M[:3, 3])),
                rotation=T["geometry_msgs/msg/Quaternion"](*(float(v) for v in q)))))
    return bytes(TYPESTORE.serialize_cdr(T[TF_TYPE](transforms=out), TF_TYPE))


def _scene_update(scene: Scene):
    """The scene's true geometry as one entity of triangle lists, in its own colours."""
    from foxglove.messages import (
        Color,
        Point3,
        Pose,
        Quaternion,
        SceneEntity,
        SceneUpdate,
        TriangleListPrimitive,
        Vector3,
    )
    triangles = []
    for mesh, rgba in scene.visual_meshes:
        if not len(mesh.faces):
            continue
        vertices = np.asarray(mesh.vertices, dtype=np.float64)
        triangles.append(TriangleListPrimitive(
            pose=Pose(position=Vector3(x=0, y=0, z=0),
                      orientation=Quaternion(x=0, y=0, z=0, w=1)),
            points=[Point3(x=float(x), y=float(y), z=float(z)) for x, y, z in vertices],
            indices=[int(i) for i in np.asarray(mesh.faces).ravel()],
            color=Color(r=rgba[0], g=rgba[1], b=rgba[2], a=rgba[3])))
    return SceneUpdate(entities=[SceneEntity(frame_id="map", id="scene", frame_locked=True,
                                             triangles=triangles)])
