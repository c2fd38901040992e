"""Plain data types that module logic takes and returns.

Each type mirrors the ROS 2 message it travels as, field for field and dtype for dtype, so that
decoding a message gives back exactly the arrays that were encoded. That is what lets the same
mission run in one process or as a process set and produce the same numbers to the last digit.

Frames: ``map`` is the world frame (z up). ``base`` is the rover body (x forward, y left, z up).
``camera`` is the optical frame of the depth camera (x right, y down, z forward), as in ROS.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from rovergate.rotations import matrix_to_quat, quat_to_matrix, quat_to_yaw, yaw_to_quat


@dataclass
class Pose:
    """A rigid transform as geometry_msgs/Pose carries it: float64 position and quaternion."""

    position: np.ndarray
    """(3,) float64, metres."""
    orientation_xyzw: np.ndarray
    """(4,) float64 unit quaternion (x, y, z, w)."""

    @classmethod
    def from_matrix(cls, T: np.ndarray) -> Pose:
        return cls(np.asarray(T[:3, 3], dtype=np.float64).copy(), matrix_to_quat(T[:3, :3]))

    @classmethod
    def from_xyz_yaw(cls, x: float, y: float, z: float, yaw: float) -> Pose:
        return cls(np.array([x, y, z], dtype=np.float64), yaw_to_quat(yaw))

    @classmethod
    def from_xyz_yaw_pitch(cls, x: float, y: float, z: float, yaw: float,
                           pitch: float) -> Pose:
        """A body pose (x forward) heading ``yaw`` and looking ``pitch`` up from level."""
        cy, sy, cp, sp = np.cos(yaw), np.sin(yaw), np.cos(pitch), np.sin(pitch)
        R = np.array([[cy * cp, -sy, -cy * sp], [sy * cp, cy, -sy * sp], [sp, 0.0, cp]])
        return cls(np.array([x, y, z], dtype=np.float64), matrix_to_quat(R))

    @property
    def pitch(self) -> float:
        """Elevation of the body's x axis above the horizontal, radians."""
        R = quat_to_matrix(self.orientation_xyzw)
        return float(np.arcsin(np.clip(R[2, 0], -1.0, 1.0)))

    def matrix(self) -> np.ndarray:
        """(4, 4) float64 homogeneous transform."""
        T = np.eye(4)
        T[:3, :3] = quat_to_matrix(self.orientation_xyzw)
        T[:3, 3] = self.position
        return T

    @property
    def yaw(self) -> float:
        return quat_to_yaw(self.orientation_xyzw)


@dataclass
class CameraIntrinsics:
    """Pinhole intrinsics as sensor_msgs/CameraInfo carries them (pixel centres at integers)."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float

    @classmethod
    def from_fov(cls, width: int, height: int, vfov_deg: float) -> CameraIntrinsics:
        fy = (height / 2.0) / np.tan(np.radians(vfov_deg) / 2.0)
        return cls(width, height, float(fy), float(fy), (width - 1) / 2.0, (height - 1) / 2.0)

    def scaled(self, factor: float) -> CameraIntrinsics:
        """The same field of view at ``factor`` times the resolution."""
        w, h = max(1, round(self.width * factor)), max(1, round(self.height * factor))
        sx, sy = w / self.width, h / self.height
        return CameraIntrinsics(w, h, self.fx * sx, self.fy * sy,
                                (self.cx + 0.5) * sx - 0.5, (self.cy + 0.5) * sy - 0.5)


@dataclass
class PoseWithCovariance:
    """A pose and its (6, 6) covariance: x, y, z in m², then rotations about x, y, z in rad²
    (``geometry_msgs/msg/PoseWithCovariance``'s order)."""

    pose: Pose
    covariance: np.ndarray


@dataclass
class SensorFrame:
    """What the rover senses at one planning step."""

    step: int
    depth_m: np.ndarray
    """(H, W) float32 z-depth in metres, NaN where there is no return."""
    intrinsics: CameraIntrinsics
    T_map_camera: Pose
    T_map_base: Pose
    covariance: np.ndarray = field(default_factory=lambda: np.zeros((6, 6)))
    """(6, 6) covariance of the published camera pose (drift model; zeros without drift)."""
    hazcams: dict[str, np.ndarray] = field(default_factory=dict)
    """The hazard cameras' depth images by name (``front``, ``rear``), degraded as the mast's;
    empty for a platform without them. Their poses follow from the base pose
    (:func:`rovergate.geometry.hazcam_from_base`)."""


#: dtype of one point of the observed surface S_t on ``map/surface``.
SURFACE_DTYPE = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("views", "<u2")])
#: dtype of one point of the learned prediction on ``map/occupancy/predicted``.
PREDICTED_DTYPE = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("probability", "<f4")])
#: dtype of one point of the planner-facing occupancy on ``map/occupancy/planner``.
PLANNER_DTYPE = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"),
                          ("source", "u1"), ("views", "<u2"), ("channels", "u1")])
#: dtype of ground-truth point clouds on ``truth/...``.
XYZ_DTYPE = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4")])


class Channel:
    """Bits of the ``channels`` field of the planner-facing occupancy: which of the planner's
    two uses of the map a point serves. Every condition but ``gated-split`` sets both."""

    GAIN = 1
    """The surface gain of candidate views (what attracts the planner)."""
    COLLISION = 2
    """Collision checking of motions (what blocks it)."""
    BOTH = GAIN | COLLISION


class Source:
    """Values of the ``source`` field of the planner-facing occupancy."""

    OBSERVED = 0
    """A point of the accumulated observed surface S_t."""
    PREDICTED = 1
    """A learned prediction the condition kept (equation 2 or the gate of equation 4)."""
    ORACLE_FN = 2
    """A reference point restored as an oracle false negative (condition ``learned+fn``)."""
    TRUTH = 3
    """A reference occupied sample (condition ``truth``); its ``views`` are those of the
    nearest S_t point within 1.5 mapper voxels (0: not observed yet)."""


def xyz(cloud: np.ndarray) -> np.ndarray:
    """(N, 3) float32 coordinates of a structured point cloud."""
    out = np.empty((len(cloud), 3), dtype=np.float32)
    out[:, 0], out[:, 1], out[:, 2] = cloud["x"], cloud["y"], cloud["z"]
    return out


def make_cloud(points_xyz: np.ndarray, dtype: np.dtype, **fields: np.ndarray) -> np.ndarray:
    """Structured cloud of ``dtype`` from (N, 3) coordinates and per-point fields."""
    out = np.zeros(len(points_xyz), dtype=dtype)
    out["x"], out["y"], out["z"] = points_xyz[:, 0], points_xyz[:, 1], points_xyz[:, 2]
    if "channels" in (dtype.names or ()):  # a planner-facing point serves both unless told
        out["channels"] = Channel.BOTH
    for name, values in fields.items():
        out[name] = values
    return out


@dataclass
class MapperOutput:
    """The mapper's products at one step."""

    step: int
    surface: np.ndarray
    """Structured (N,) :data:`SURFACE_DTYPE`: S_t, new voxels appended at the end."""
    predicted: np.ndarray
    """Structured (M,) :data:`PREDICTED_DTYPE`: points with occupancy probability >= 0.5."""


@dataclass
class PlannerMap:
    """The planner-facing occupancy of one step."""

    step: int
    points: np.ndarray
    """Structured (N,) :data:`PLANNER_DTYPE`."""
    suppressed: int = 0
    """Predicted points the gate suppressed this step (0 when no gate runs; under
    ``gated-split``, those withheld from the gain channel)."""

    def serving(self, channel: int) -> PlannerMap:
        """The map as one of the planner's uses sees it: the points that serve ``channel``
        (:class:`Channel`)."""
        return PlannerMap(self.step, self.points[(self.points["channels"] & channel) != 0],
                          self.suppressed)

    def within(self, x: float, y: float, half_m: float) -> tuple[PlannerMap, np.ndarray | None]:
        """The map's points in the square of half-side ``half_m`` around (x, y), and their
        indices in :attr:`points` (None, and the map itself, when it holds every point)."""
        p = self.points
        keep = ((np.abs(p["x"] - np.float32(x)) <= half_m)
                & (np.abs(p["y"] - np.float32(y)) <= half_m))
        if keep.all():
            return self, None
        index = np.flatnonzero(keep)
        return PlannerMap(self.step, p[index], self.suppressed), index


_NO_RUNS = np.zeros(0, dtype=np.uint32)


def step_and_cloud(value: tuple[int, np.ndarray] | PlannerMap) -> tuple[int, np.ndarray]:
    """``(step, cloud)`` of a map value a module publishes: ``(step, cloud)``, or a
    :class:`PlannerMap`."""
    if isinstance(value, PlannerMap):
        return value.step, value.points
    return int(value[0]), value[1]


@dataclass
class CloudUpdate:
    """One step of an incremental map topic as it travels (``rovergate_msgs/msg/CloudUpdate``,
    :mod:`rovergate.streams`): the cloud of ``step`` whole (a keyframe) or as what changed
    since the publisher's cloud of ``base_step``."""

    step: int
    base_step: int
    """-1: a keyframe (``points`` is the whole cloud); else the step of the base cloud."""
    size: int
    """Points of the cloud it makes."""
    points: np.ndarray
    """Structured points of the topic's dtype that are not copied from the base."""
    put_at: np.ndarray = field(default_factory=lambda: _NO_RUNS)
    """(len(points),) uint32: where each of ``points`` goes (empty on a keyframe)."""
    copy_to: np.ndarray = field(default_factory=lambda: _NO_RUNS)
    """(R,) uint32: the first position in the new cloud of each run copied from the base."""
    copy_from: np.ndarray = field(default_factory=lambda: _NO_RUNS)
    """(R,) uint32: the first point of the base of each run."""
    copy_count: np.ndarray = field(default_factory=lambda: _NO_RUNS)
    """(R,) uint32: the points of each run."""
    patch_at: np.ndarray = field(default_factory=lambda: _NO_RUNS)
    """(P,) uint32: positions whose point is copied but whose other fields change."""
    patches: np.ndarray | None = None
    """(P,) structured: the new values of the fields other than x, y, z at ``patch_at``
    (None: no patch)."""

    @property
    def keyframe(self) -> bool:
        return self.base_step < 0


@dataclass
class PlanPath:
    """The motion chosen for the next step, as rover base poses in ``map``."""

    step: int
    poses: list[Pose] = field(default_factory=list)


@dataclass
class ExecutionReport:
    """What executing one step's path did in the true world."""

    step: int
    collided: bool
    collision_samples: int
    min_clearance_m: float
    path_length_m: float
    executed_fraction: float
    untraversable: bool = False
    pose_error_m: float = 0.0
    contact: tuple[float, float, float] | None = None
    """Where the body first touched the true scene, in the frame of the published poses
    (``map`` as the platform believes it); None without a collision."""


@dataclass
class TraverseReport:
    """What the planner's traversability layer refused in one step, and what it chose."""

    step: int
    refused: dict[str, int] = field(default_factory=dict)
    """Motions refused by hazard (``unknown``, ``wheel-drop``, ``tilt``, ``belly``)."""
    reason: str = ""
    """The planner's choice: best-feasible, rotate, escape, backout or stay."""
    known_cells: int = 0
    gain_points: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.uint32))
    """(K,) uint32 indices into the step's planner map: the points the gain of the view from
    the chosen goal counts (its gain is K)."""


@dataclass
class TraversabilityGrid:
    """The traversability map around the rover as ``nav_msgs/OccupancyGrid`` carries it: -1
    unknown, 0 known and clear, 100 an obstacle to the body (row-major from the corner at
    ``origin_xy``, rows along y)."""

    step: int
    cells: np.ndarray
    """(H, W) int8."""
    resolution_m: float
    origin_xy: tuple[float, float]


@dataclass
class MissionStatus:
    """The mission clock and its headline figures."""

    step: int
    steps_total: int
    state: str
    condition: str
    coverage: float
    collisions: int


@dataclass
class StepTiming:
    """How long a module worked on one step."""

    step: int
    module: str
    compute_s: float
    dropped_total: int


# --- the ground link (mission/link/bridge.py, mission/link/ground.py) ------------------------

@dataclass
class TelemetryFrame:
    """One downlinked item of the onboard queue, as the ground receives it."""

    seq: int
    kind: str
    """status, pose, map, event or command_ack."""
    msgtype: str
    """ROS 2 type of ``payload``."""
    step: int
    radiated_s: float
    """Simulated time at which the rover radiated it."""
    payload: bytes
    """CDR bytes of a ``msgtype`` message."""


@dataclass
class DownlinkAck:
    """The ground's acknowledgement of downlinked sequence numbers."""

    seqs: list[int]


@dataclass
class GroundCommand:
    """A command from the ground station."""

    id: int
    verb: str
    """pause, resume, abort, set, condition or planner."""
    args: list[str] = field(default_factory=list)


@dataclass
class CommandAck:
    """What the rover did with a ground command (downlinked as ``command_ack``)."""

    id: int
    verb: str
    state: str
    """executed or rejected."""
    step: int
    received_s: float
    detail: str = ""


@dataclass
class MissionEvent:
    """Something the ground should know (downlinked as ``event``; never dropped)."""

    step: int
    kind: str
    detail: str = ""
