"""ROS 2 message types and their CDR codec, built on ``rosbags``.

Standard types are used where one fits; the three project types (``rovergate_msgs/msg/...``)
are defined in ``rovergate/msg/*.msg`` and registered with the rosbags type store here.

Where the planning step travels: every message has a ``std_msgs/Header`` whose
``stamp.sec`` is the planning step t (the mission clock ticks one second per step, and
``stamp.nanosec`` is 0); the project types repeat it in a ``step`` field. Frame ids are
``map`` for everything in the world frame and ``camera`` for images and intrinsics.

:func:`encode` and :func:`decode` convert between bytes on the wire and the plain data types of
:mod:`rovergate.types`. :func:`decode` raises :class:`MessageError` with a one-line reason for
anything that does not decode or has the wrong type or shape.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from importlib import resources
from typing import Any

import numpy as np
from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from rosbags.typesys.store import Typestore

from rovergate.graph import CLOUD_UPDATE, TOPICS
from rovergate.types import (
    PLANNER_DTYPE,
    PREDICTED_DTYPE,
    SURFACE_DTYPE,
    XYZ_DTYPE,
    CameraIntrinsics,
    CloudUpdate,
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
    step_and_cloud,
)

PROJECT_TYPES = ("CloudUpdate", "MissionStatus", "ExecutionReport", "StepTiming", "TelemetryFrame",
                 "DownlinkAck", "GroundCommand", "CommandAck", "MissionEvent",
                 "TraverseReport")


#: The largest messages a reader accepts. A payload over MAX_PAYLOAD_BYTES is refused before
#: it is parsed, and a declared point count, image size or path length over its limit before
#: its arrays are built: a forged header cannot make a module allocate more than the bytes it
#: was sent.
MAX_PAYLOAD_BYTES = 512 * 2**20
MAX_POINTS = 10_000_000
MAX_IMAGE_PIXELS = 4096 * 4096
MAX_PATH_POSES = 10_000


#: A message of the typestore: rosbags generates its classes at run time, so they are typed
#: as Any here; every decoder checks what it reads.
RosMsg = Any


class MessageError(ValueError):
    """A message that does not decode, or decodes to the wrong type or shape."""


def _build_typestore() -> Typestore:
    store = get_typestore(Stores.ROS2_HUMBLE)
    types = {}
    for name in PROJECT_TYPES:
        text = resources.files("rovergate").joinpath(f"msg/{name}.msg").read_text()
        types.update(get_types_from_msg(text, f"rovergate_msgs/msg/{name}"))
    store.register(types)
    return store


TYPESTORE = _build_typestore()
_T = TYPESTORE.types

# PointField datatypes (sensor_msgs/msg/PointField) and the numpy kinds they map to.
_POINTFIELD = {1: "i1", 2: "u1", 3: "<i2", 4: "<u2", 5: "<i4", 6: "<u4", 7: "<f4", 8: "<f8"}
_POINTFIELD_INV = {np.dtype(v).str: k for k, v in _POINTFIELD.items()}


def _header(step: int, frame_id: str = "map") -> RosMsg:
    return _T["std_msgs/msg/Header"](
        stamp=_T["builtin_interfaces/msg/Time"](sec=int(step), nanosec=0), frame_id=frame_id)


def _step(header: RosMsg) -> int:
    return int(header.stamp.sec)


# --- images ---------------------------------------------------------------------------------

def depth_to_ros(step: int, depth_m: np.ndarray, frame_id: str = "camera") -> RosMsg:
    depth = np.ascontiguousarray(depth_m, dtype="<f4")
    h, w = depth.shape
    return _T["sensor_msgs/msg/Image"](
        header=_header(step, frame_id), height=h, width=w, encoding="32FC1", is_bigendian=0,
        step=4 * w, data=depth.view(np.uint8).ravel())


def hazcam_from_ros(msg: RosMsg) -> tuple[int, np.ndarray]:
    """A hazard camera's depth: as :func:`depth_from_ros`, and 0 x 0 (a platform without
    hazard cameras) is a valid, empty image."""
    if msg.height == 0 and msg.width == 0 and len(msg.data) == 0 and msg.encoding == "32FC1":
        return _step(msg.header), np.zeros((0, 0), dtype=np.float32)
    return depth_from_ros(msg)


def depth_from_ros(msg: RosMsg) -> tuple[int, np.ndarray]:
    if msg.encoding != "32FC1":
        raise MessageError(f"depth image encoding is {msg.encoding!r}, expected '32FC1'")
    if msg.is_bigendian:
        raise MessageError("depth image is big-endian, expected little-endian")
    h, w = int(msg.height), int(msg.width)
    if h * w > MAX_IMAGE_PIXELS:
        raise MessageError(f"depth image of {w}x{h} is over the limit of {MAX_IMAGE_PIXELS} "
                           "pixels")
    if h == 0 or w == 0 or msg.step != 4 * w or len(msg.data) != 4 * w * h:
        raise MessageError(f"depth image of {w}x{h} with row step {msg.step} carries "
                           f"{len(msg.data)} bytes, expected {4 * w * h}")
    return _step(msg.header), np.frombuffer(msg.data.tobytes(), dtype="<f4").reshape(h, w).copy()


# --- camera info ----------------------------------------------------------------------------

def camera_info_to_ros(step: int, k: CameraIntrinsics, frame_id: str = "camera") -> RosMsg:
    K = np.array([k.fx, 0, k.cx, 0, k.fy, k.cy, 0, 0, 1], dtype=np.float64)
    P = np.array([k.fx, 0, k.cx, 0, 0, k.fy, k.cy, 0, 0, 0, 1, 0], dtype=np.float64)
    roi = _T["sensor_msgs/msg/RegionOfInterest"](
        x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
    return _T["sensor_msgs/msg/CameraInfo"](
        header=_header(step, frame_id), height=k.height, width=k.width,
        distortion_model="plumb_bob", d=np.zeros(5), k=K, r=np.eye(3).ravel(), p=P,
        binning_x=0, binning_y=0, roi=roi)


def camera_info_from_ros(msg: RosMsg) -> tuple[int, CameraIntrinsics]:
    K = np.asarray(msg.k, dtype=np.float64)
    if K.shape != (9,) or not np.all(np.isfinite(K)) or K[0] <= 0 or K[4] <= 0 \
            or msg.width == 0 or msg.height == 0:
        raise MessageError("camera info has no valid intrinsics (k must hold finite fx, "
                           "fy > 0)")
    if int(msg.width) * int(msg.height) > MAX_IMAGE_PIXELS:
        raise MessageError(f"camera info of {msg.width}x{msg.height} is over the limit of "
                           f"{MAX_IMAGE_PIXELS} pixels")
    return _step(msg.header), CameraIntrinsics(int(msg.width), int(msg.height), float(K[0]),
                                               float(K[4]), float(K[2]), float(K[5]))


# --- poses and paths ------------------------------------------------------------------------

def _pose_msg(pose: Pose) -> RosMsg:
    p, q = pose.position, pose.orientation_xyzw
    return _T["geometry_msgs/msg/Pose"](
        position=_T["geometry_msgs/msg/Point"](x=float(p[0]), y=float(p[1]), z=float(p[2])),
        orientation=_T["geometry_msgs/msg/Quaternion"](
            x=float(q[0]), y=float(q[1]), z=float(q[2]), w=float(q[3])))


def _pose_from_msg(msg: RosMsg) -> Pose:
    p, q = msg.position, msg.orientation
    quat = np.array([q.x, q.y, q.z, q.w], dtype=np.float64)
    values = np.array([p.x, p.y, p.z, *quat])
    if not np.all(np.isfinite(values)):
        raise MessageError("pose holds a non-finite value")
    with np.errstate(over="ignore"):  # a forged 1e308 has an infinite norm: refused below
        norm = float(np.linalg.norm(quat))
    if abs(norm - 1.0) > 1e-3:
        raise MessageError(f"pose quaternion has norm {norm:.4f}, expected 1")
    return Pose(np.array([p.x, p.y, p.z], dtype=np.float64), quat)


def pose_to_ros(step: int, pose: Pose) -> RosMsg:
    return _T["geometry_msgs/msg/PoseStamped"](header=_header(step), pose=_pose_msg(pose))


def pose_from_ros(msg: RosMsg) -> tuple[int, Pose]:
    return _step(msg.header), _pose_from_msg(msg.pose)


def pose_cov_to_ros(step: int, value: PoseWithCovariance) -> RosMsg:
    return _T["geometry_msgs/msg/PoseWithCovarianceStamped"](
        header=_header(step), pose=_T["geometry_msgs/msg/PoseWithCovariance"](
            pose=_pose_msg(value.pose),
            covariance=np.ascontiguousarray(value.covariance, dtype=np.float64).ravel()))


def pose_cov_from_ros(msg: RosMsg) -> tuple[int, PoseWithCovariance]:
    cov = np.asarray(msg.pose.covariance, dtype=np.float64)
    if cov.shape != (36,) or not np.all(np.isfinite(cov)):
        raise MessageError("pose covariance must be 36 finite values")
    cov = cov.reshape(6, 6)
    if np.any(np.diag(cov) < 0) or not np.allclose(cov, cov.T):
        raise MessageError("pose covariance must be symmetric with a non-negative diagonal")
    return _step(msg.header), PoseWithCovariance(_pose_from_msg(msg.pose.pose), cov)


def path_to_ros(path: PlanPath) -> RosMsg:
    poses = [_T["geometry_msgs/msg/PoseStamped"](header=_header(path.step), pose=_pose_msg(p))
             for p in path.poses]
    return _T["nav_msgs/msg/Path"](header=_header(path.step), poses=poses)


def path_from_ros(msg: RosMsg) -> PlanPath:
    if len(msg.poses) > MAX_PATH_POSES:
        raise MessageError(f"path of {len(msg.poses)} poses is over the limit of "
                           f"{MAX_PATH_POSES}")
    return PlanPath(_step(msg.header), [_pose_from_msg(p.pose) for p in msg.poses])


# --- point clouds ---------------------------------------------------------------------------

def _structured(dt: np.dtype) -> tuple[tuple[str, ...], Any]:
    """The field names and fields of a structured dtype."""
    if dt.names is None or dt.fields is None:
        raise MessageError(f"dtype {dt} is not a structured dtype")
    return dt.names, dt.fields


def cloud_to_ros(step: int, cloud: np.ndarray) -> RosMsg:
    """Structured numpy array -> sensor_msgs/PointCloud2 (one row, little-endian, packed)."""
    dt = cloud.dtype
    names, dt_fields = _structured(dt)
    fields = [_T["sensor_msgs/msg/PointField"](
        name=name, offset=dt_fields[name][1], datatype=_POINTFIELD_INV[dt_fields[name][0].str],
        count=1) for name in names]
    n = len(cloud)
    return _T["sensor_msgs/msg/PointCloud2"](
        header=_header(step), height=1, width=n, fields=fields, is_bigendian=False,
        point_step=dt.itemsize, row_step=dt.itemsize * n,
        data=np.ascontiguousarray(cloud).view(np.uint8).ravel(), is_dense=True)


def cloud_cdr(step: int, cloud: np.ndarray) -> bytes:
    """A cloud as the CDR bytes of a sensor_msgs/PointCloud2."""
    return bytes(TYPESTORE.serialize_cdr(cloud_to_ros(step, cloud), "sensor_msgs/msg/PointCloud2"))


def cloud_from_ros(msg: RosMsg, expected: np.dtype) -> tuple[int, np.ndarray]:
    """sensor_msgs/PointCloud2 -> structured array of ``expected`` dtype, checked field by field."""
    if int(msg.width) * int(msg.height) > MAX_POINTS:
        raise MessageError(f"point cloud of {int(msg.width) * int(msg.height)} points is over "
                           f"the limit of {MAX_POINTS}")
    names, fields = _structured(expected)
    got = {f.name: (int(f.offset), int(f.datatype), int(f.count)) for f in msg.fields}
    for name in names:
        if name not in got:
            raise MessageError(f"point cloud lacks field {name!r} (has {sorted(got)})")
        offset, datatype, count = got[name]
        want = _POINTFIELD_INV[fields[name][0].str]
        if datatype != want or count != 1:
            raise MessageError(f"point cloud field {name!r} has datatype {datatype} x{count}, "
                               f"expected {want} x1")
    if msg.is_bigendian:
        raise MessageError("point cloud is big-endian, expected little-endian")
    n = int(msg.width) * int(msg.height)
    step = int(msg.point_step)
    if len(msg.data) != n * step:
        raise MessageError(f"point cloud of {n} points x {step} bytes carries "
                           f"{len(msg.data)} bytes")
    layout: Any = {"names": list(names),
              "formats": [fields[k][0] for k in names],
              "offsets": [got[k][0] for k in names], "itemsize": step}
    wire = np.dtype(layout)
    if wire == expected:  # our own layout (every rovergate publisher): one copy of the bytes
        return _step(msg.header), np.array(msg.data, dtype=np.uint8, copy=True).view(expected)
    raw = np.frombuffer(msg.data.tobytes(), dtype=wire, count=n)
    out = np.empty(n, dtype=expected)
    for name in names:
        out[name] = raw[name]
    return _step(msg.header), out


# --- project types --------------------------------------------------------------------------

def status_to_ros(s: MissionStatus) -> RosMsg:
    return _T["rovergate_msgs/msg/MissionStatus"](
        header=_header(s.step), step=s.step, steps_total=s.steps_total, state=s.state,
        condition=s.condition, coverage=float(s.coverage), collisions=s.collisions)


def status_from_ros(m: RosMsg) -> MissionStatus:
    return MissionStatus(int(m.step), int(m.steps_total), str(m.state), str(m.condition),
                         float(m.coverage), int(m.collisions))


def execution_to_ros(r: ExecutionReport) -> RosMsg:
    return _T["rovergate_msgs/msg/ExecutionReport"](
        header=_header(r.step), step=r.step, collided=bool(r.collided),
        collision_samples=r.collision_samples, min_clearance_m=float(r.min_clearance_m),
        path_length_m=float(r.path_length_m), executed_fraction=float(r.executed_fraction),
        untraversable=bool(r.untraversable), pose_error_m=float(r.pose_error_m),
        contact=_T["geometry_msgs/msg/Point"](
            *(float(v) for v in (r.contact if r.contact is not None else (np.nan,) * 3))))


def execution_from_ros(m: RosMsg) -> ExecutionReport:
    return ExecutionReport(int(m.step), bool(m.collided), int(m.collision_samples),
                           float(m.min_clearance_m), float(m.path_length_m),
                           float(m.executed_fraction), bool(m.untraversable),
                           float(m.pose_error_m), _contact(m.contact))


def _contact(p: RosMsg) -> tuple[float, float, float] | None:
    xyz = (float(p.x), float(p.y), float(p.z))
    return None if np.isnan(xyz[0]) else xyz


_HAZARD_FIELDS = {"unknown": "refused_unknown", "wheel-drop": "refused_wheel_drop",
                  "tilt": "refused_tilt", "belly": "refused_belly"}


def traverse_to_ros(r: TraverseReport) -> RosMsg:
    return _T["rovergate_msgs/msg/TraverseReport"](
        header=_header(r.step), step=r.step, reason=r.reason, known_cells=int(r.known_cells),
        gain_points=np.ascontiguousarray(r.gain_points, dtype=np.uint32),
        **{f: int(r.refused.get(k, 0)) for k, f in _HAZARD_FIELDS.items()})


def traverse_from_ros(m: RosMsg) -> TraverseReport:
    return TraverseReport(int(m.step), {k: int(getattr(m, f)) for k, f in _HAZARD_FIELDS.items()},
                          str(m.reason), int(m.known_cells),
                          np.asarray(m.gain_points, dtype=np.uint32))


def grid_to_ros(g: TraversabilityGrid) -> RosMsg:
    h, w = g.cells.shape
    origin = _T["geometry_msgs/msg/Pose"](
        position=_T["geometry_msgs/msg/Point"](x=float(g.origin_xy[0]), y=float(g.origin_xy[1]),
                                               z=0.0),
        orientation=_T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0))
    info = _T["nav_msgs/msg/MapMetaData"](
        map_load_time=_T["builtin_interfaces/msg/Time"](sec=int(g.step), nanosec=0),
        resolution=float(g.resolution_m), width=w, height=h, origin=origin)
    return _T["nav_msgs/msg/OccupancyGrid"](
        header=_header(g.step), info=info,
        data=np.ascontiguousarray(g.cells, dtype=np.int8).ravel())


def grid_from_ros(m: RosMsg) -> TraversabilityGrid:
    h, w = int(m.info.height), int(m.info.width)
    if h * w > MAX_IMAGE_PIXELS or len(m.data) != h * w:
        raise MessageError(f"occupancy grid of {w}x{h} carries {len(m.data)} cells")
    return TraversabilityGrid(_step(m.header), np.asarray(m.data, dtype=np.int8).reshape(h, w),
                              float(m.info.resolution),
                              (float(m.info.origin.position.x), float(m.info.origin.position.y)))


def timing_to_ros(t: StepTiming) -> RosMsg:
    return _T["rovergate_msgs/msg/StepTiming"](
        header=_header(t.step), step=t.step, module=t.module, compute_s=float(t.compute_s),
        dropped_total=t.dropped_total)


def timing_from_ros(m: RosMsg) -> StepTiming:
    return StepTiming(int(m.step), str(m.module), float(m.compute_s), int(m.dropped_total))


# --- the ground link ------------------------------------------------------------------------

def frame_to_ros(f: TelemetryFrame) -> RosMsg:
    return _T["rovergate_msgs/msg/TelemetryFrame"](
        header=_header(f.step), seq=f.seq, kind=f.kind, msgtype=f.msgtype, step=f.step,
        radiated_s=float(f.radiated_s), payload=np.frombuffer(f.payload, dtype=np.uint8))


def frame_from_ros(m: RosMsg) -> TelemetryFrame:
    return TelemetryFrame(int(m.seq), str(m.kind), str(m.msgtype), int(m.step),
                          float(m.radiated_s), m.payload.tobytes())


def ack_to_ros(a: DownlinkAck) -> RosMsg:
    return _T["rovergate_msgs/msg/DownlinkAck"](
        header=_header(0), seqs=np.asarray(a.seqs, dtype=np.uint64))


def ack_from_ros(m: RosMsg) -> tuple[int, DownlinkAck]:
    return 0, DownlinkAck([int(s) for s in m.seqs])


def command_to_ros(c: GroundCommand) -> RosMsg:
    return _T["rovergate_msgs/msg/GroundCommand"](header=_header(0), id=c.id, verb=c.verb,
                                                  args=list(c.args))


def command_from_ros(m: RosMsg) -> tuple[int, GroundCommand]:
    return 0, GroundCommand(int(m.id), str(m.verb), [str(a) for a in m.args])


def command_ack_to_ros(a: CommandAck) -> RosMsg:
    return _T["rovergate_msgs/msg/CommandAck"](
        header=_header(a.step), id=a.id, verb=a.verb, state=a.state, step=a.step,
        received_s=float(a.received_s), detail=a.detail)


def command_ack_from_ros(m: RosMsg) -> CommandAck:
    return CommandAck(int(m.id), str(m.verb), str(m.state), int(m.step), float(m.received_s),
                      str(m.detail))


def event_to_ros(e: MissionEvent) -> RosMsg:
    return _T["rovergate_msgs/msg/MissionEvent"](header=_header(e.step), step=e.step,
                                                 kind=e.kind, detail=e.detail)


def event_from_ros(m: RosMsg) -> MissionEvent:
    return MissionEvent(int(m.step), str(m.kind), str(m.detail))


# --- the table: topic -> (to_ros, from_ros) -------------------------------------------------
# ``to_ros`` takes the value a module publishes; ``from_ros`` returns (step, value).

def _with_step(from_ros: Callable[[Any], Any]) -> Callable[[Any], tuple[int, Any]]:
    def decode_with_step(msg: RosMsg) -> tuple[int, Any]:
        value = from_ros(msg)
        return value.step, value
    return decode_with_step


def update_to_ros(update: CloudUpdate | tuple[int, np.ndarray] | PlannerMap) -> RosMsg:
    """A :class:`rovergate.types.CloudUpdate` -> rovergate_msgs/CloudUpdate; a whole value
    (``(step, cloud)`` or a PlannerMap) is sent as a keyframe."""
    if not isinstance(update, CloudUpdate):
        step, cloud = step_and_cloud(update)
        update = CloudUpdate(step, -1, len(cloud), cloud)
    u32 = np.uint32
    return _T[CLOUD_UPDATE](
        header=_header(update.step), base_step=int(update.base_step), size=int(update.size),
        copy_to=np.asarray(update.copy_to, dtype=u32),
        copy_from=np.asarray(update.copy_from, dtype=u32),
        copy_count=np.asarray(update.copy_count, dtype=u32),
        put_at=np.asarray(update.put_at, dtype=u32),
        points=cloud_to_ros(update.step, update.points),
        patch_at=np.asarray(update.patch_at, dtype=u32),
        patches=cloud_to_ros(update.step, _patches(update)))


def patch_dtype(dtype: np.dtype) -> np.dtype:
    """The fields of a cloud's dtype other than x, y, z (what a CloudUpdate patches)."""
    names = [n for n in dtype.names or () if n not in ("x", "y", "z")]
    return np.dtype([(n, dtype.fields[n][0]) for n in names])  # type: ignore[index]


def _patches(update: CloudUpdate) -> np.ndarray:
    if update.patches is not None:
        return update.patches
    return np.empty(0, dtype=patch_dtype(update.points.dtype))


def _update_from_ros(dtype: np.dtype) -> Callable[[RosMsg], tuple[int, CloudUpdate]]:
    def from_ros(msg: RosMsg) -> tuple[int, CloudUpdate]:
        step = _step(msg.header)
        if int(msg.size) > MAX_POINTS:
            raise MessageError(f"cloud update of {int(msg.size)} points is over the limit of "
                               f"{MAX_POINTS}")
        _, points = cloud_from_ros(msg.points, dtype)
        base = int(msg.base_step)
        if base >= step:
            raise MessageError(f"cloud update of step {step} is made from step {base}, not an "
                               "earlier one")

        def table(a: Any) -> np.ndarray:
            return np.asarray(a, dtype=np.uint32)
        _, patches = cloud_from_ros(msg.patches, patch_dtype(dtype))
        return step, CloudUpdate(step, base, int(msg.size), points, table(msg.put_at),
                                 table(msg.copy_to), table(msg.copy_from),
                                 table(msg.copy_count), table(msg.patch_at), patches)
    return from_ros


def _in_frame(to_ros: Callable[..., RosMsg], frame_id: str) -> Callable[[Any], RosMsg]:
    """An encoder of ``(step, value)`` by ``to_ros`` in frame ``frame_id``."""
    def encode(v: tuple[int, Any]) -> RosMsg:
        return to_ros(v[0], v[1], frame_id=frame_id)
    return encode


def _cloud_codec(dtype: np.dtype) -> tuple[Callable[[Any], RosMsg],
                                          Callable[[Any], tuple[int, np.ndarray]]]:
    return (lambda v: cloud_to_ros(*v), lambda m: cloud_from_ros(m, dtype))


_CODECS: dict[str, tuple[Callable[[Any], Any], Callable[[Any], tuple[int, Any]]]] = {
    "depth": (lambda v: depth_to_ros(*v), depth_from_ros),
    "camera_info": (lambda v: camera_info_to_ros(*v), camera_info_from_ros),
    **{f"hazcam_{end}": (_in_frame(depth_to_ros, f"hazcam_{end}_optical"), hazcam_from_ros)
       for end in ("front", "rear")},
    **{f"hazcam_{end}_info": (_in_frame(camera_info_to_ros, f"hazcam_{end}_optical"),
                              camera_info_from_ros) for end in ("front", "rear")},
    "pose": (lambda v: pose_to_ros(*v), pose_from_ros),
    "pose_cov": (lambda v: pose_cov_to_ros(*v), pose_cov_from_ros),
    "base_pose": (lambda v: pose_to_ros(*v), pose_from_ros),
    # The incremental maps (rovergate.streams): a CloudUpdate, or a whole value as a keyframe.
    "surface": (update_to_ros, _update_from_ros(SURFACE_DTYPE)),
    "predicted": (update_to_ros, _update_from_ros(PREDICTED_DTYPE)),
    "planner_map": (update_to_ros, _update_from_ros(PLANNER_DTYPE)),
    "path": (path_to_ros, _with_step(path_from_ros)),
    "rejected": (path_to_ros, _with_step(path_from_ros)),
    "execution": (execution_to_ros, _with_step(execution_from_ros)),
    "traverse": (traverse_to_ros, _with_step(traverse_from_ros)),
    "traversability": (grid_to_ros, _with_step(grid_from_ros)),
    "status": (status_to_ros, _with_step(status_from_ros)),
    "timing": (timing_to_ros, _with_step(timing_from_ros)),
    "truth_surface": _cloud_codec(XYZ_DTYPE),
    "truth_occupancy": _cloud_codec(XYZ_DTYPE),
    "downlink": (frame_to_ros, _with_step(frame_from_ros)),
    "downlink_ack": (ack_to_ros, ack_from_ros),
    "uplink": (command_to_ros, command_from_ros),
    "uplink_report": (command_ack_to_ros, _with_step(command_ack_from_ros)),
}

#: What a telemetry item of each kind carries: (ROS 2 type, to_ros, from_ros -> value).
ITEM_TYPES: dict[str, tuple[str, Callable[[Any], Any], Callable[[Any], Any]]] = {
    "status": ("rovergate_msgs/msg/MissionStatus", status_to_ros, status_from_ros),
    "pose": ("geometry_msgs/msg/PoseStamped", lambda v: pose_to_ros(*v),
             lambda m: pose_from_ros(m)[1]),
    "map": ("sensor_msgs/msg/PointCloud2", lambda v: cloud_to_ros(*v),
            lambda m: cloud_from_ros(m, SURFACE_DTYPE)[1]),
    "event": ("rovergate_msgs/msg/MissionEvent", event_to_ros, event_from_ros),
    "command_ack": ("rovergate_msgs/msg/CommandAck", command_ack_to_ros,
                    command_ack_from_ros),
}


def encode_item(kind: str, value: Any) -> tuple[str, bytes]:
    """A telemetry item's (ROS 2 type, CDR bytes); ``pose`` and ``map`` take (step, value)."""
    msgtype, to_ros, _ = ITEM_TYPES[kind]
    return msgtype, bytes(TYPESTORE.serialize_cdr(to_ros(value), msgtype))


def decode_item(kind: str, msgtype: str, payload: bytes) -> Any:
    """The value of a downlinked item. Raises :class:`MessageError` on anything malformed."""
    if len(payload) > MAX_PAYLOAD_BYTES:
        raise MessageError(f"telemetry item of {len(payload)} bytes is over the limit of "
                           f"{MAX_PAYLOAD_BYTES}")
    if kind not in ITEM_TYPES or ITEM_TYPES[kind][0] != msgtype:
        raise MessageError(f"telemetry item of kind {kind!r} with type {msgtype!r} is not one "
                           "this version knows")
    try:
        return ITEM_TYPES[kind][2](TYPESTORE.deserialize_cdr(payload, msgtype))
    except MessageError:
        raise
    except Exception as exc:
        raise MessageError(f"not a valid CDR {msgtype}: {exc}") from None


#: Topics whose value is written ``(step, value)``; the others carry their step themselves.
_STEP_PAIRS = frozenset({"depth", "camera_info", "hazcam_front", "hazcam_rear",
                         "hazcam_front_info", "hazcam_rear_info", "pose", "pose_cov",
                         "base_pose", "surface", "predicted", "truth_surface",
                         "truth_occupancy"})


def stamped(topic: str, value: Any) -> tuple[int, Any]:
    """``(step, value as a reader receives it)`` of a value written for ``topic``: what
    :func:`decode` gives back from :func:`encode`'s bytes, without the bytes."""
    if topic in _STEP_PAIRS:
        return (int(value[0]), value[1])
    return value.step, value


def prepare(topics: Iterable[str]) -> None:
    """Build the CDR codecs of ``topics`` now. rosbags generates a type's serialiser on its
    first use, 4 to 11 ms each: a module prepares its topics before it declares itself ready,
    so that its first step does not pay for it (the first step of a process set took 150 ms
    more than the others)."""
    for msgtype in {TOPICS[t].msgtype for t in topics}:
        TYPESTORE.get_msgdef(msgtype)


def encode(topic: str, value: Any) -> bytes:
    """Serialise a module's value for ``topic`` as CDR bytes of the topic's ROS 2 type.

    Depth, camera info, poses and clouds take ``(step, value)``; the others carry their step.
    """
    to_ros, _ = _CODECS[topic]
    return bytes(TYPESTORE.serialize_cdr(to_ros(value), TOPICS[topic].msgtype))


def decode(topic: str, payload: bytes) -> tuple[int, Any]:
    """CDR bytes -> (step, value). Raises :class:`MessageError` on anything malformed."""
    msgtype = TOPICS[topic].msgtype
    if len(payload) > MAX_PAYLOAD_BYTES:
        raise MessageError(f"{msgtype} of {len(payload)} bytes is over the limit of "
                           f"{MAX_PAYLOAD_BYTES}")
    try:
        msg = TYPESTORE.deserialize_cdr(payload, msgtype)
    except Exception as exc:  # rosbags raises several kinds for truncated or garbage bytes
        raise MessageError(f"not a valid CDR {msgtype}: {exc}") from None
    _, from_ros = _CODECS[topic]
    try:
        return from_ros(msg)
    except MessageError:
        raise
    except Exception as exc:
        raise MessageError(f"{msgtype} has the wrong shape: {exc}") from None
