"""The process graph, declared once: every topic, and every module with what it consumes and
produces.

This is where a reader learns every topic of the system. Everything else is derived from it:
the keys (:class:`rovergate.keys.Keys`), each node's subscriptions and publishers
(:class:`rovergate.node.ModuleNode`), the in-process transport's routing
(:mod:`mission.runtime.transport`), the mission's inbox and journal (which topics it watches,
keeps for every step, or keeps for the last few), which module reports each timing stage, what a
restarted module replays, and the topic table of docs/architecture.md (a test checks it against
:func:`topic_table`). Adding a topic is one entry in :data:`TOPICS` plus its codec in
:mod:`rovergate.messages`; wiring it is one name in a module's ``inputs`` or ``outputs``.

A module handles step t when all its inputs for step t are in: an input with ``lag=1`` is the
message of step t-1 (absent at t=0). Outputs are listed in the order a module publishes them;
the last one marks a step as handled (a restarted module resumes at the last step whose last
output the mission saw).

Run ``python -m rovergate.graph`` to print the topic table.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Literal

#: The rover's network (its processes and subscribers) or the ground network (the ground
#: station and the mission manager's bridge, under the ground namespace).
Network = Literal["rover", "ground"]
#: How a topic travels: published samples, a queryable answered on request, or a liveliness
#: token.
Kind = Literal["topic", "queryable", "liveliness"]


@dataclass(frozen=True)
class Topic:
    """A key (relative to its network's namespace) and the ROS 2 message type carried on it."""

    suffix: str
    msgtype: str
    doc: str
    network: Network = "rover"
    kind: Kind = "topic"
    incremental: bool = False
    """A map that travels as what changed since the step before (:mod:`rovergate.streams`):
    its ``msgtype`` is ``rovergate_msgs/msg/CloudUpdate``, whose ``points`` are the cloud's."""


#: The type of the incremental maps: a keyframe or the change since the step before, whose
#: ``points`` is a ``sensor_msgs/msg/PointCloud2`` (:mod:`rovergate.streams`).
CLOUD_UPDATE = "rovergate_msgs/msg/CloudUpdate"

#: Every topic of the system. docs/architecture.md's topic table lists the same entries.
TOPICS: dict[str, Topic] = {
    "depth": Topic("sensor/depth", "sensor_msgs/msg/Image",
                   "depth in metres (32FC1), REP 117: +Inf where nothing is within the "
                   "maximum range, NaN where the return is invalid (dropped, too near)"),
    "camera_info": Topic("sensor/camera_info", "sensor_msgs/msg/CameraInfo",
                         "intrinsics (`k`), pixel centres at integers"),
    "pose": Topic("sensor/pose", "geometry_msgs/msg/PoseStamped",
                  "camera pose (optical frame: x right, y down, z forward) in frame `map`"),
    "pose_cov": Topic("sensor/pose_with_covariance",
                      "geometry_msgs/msg/PoseWithCovarianceStamped",
                      "`pose` with its covariance (x, y, z, rotations about x, y, z) as the "
                      "drift model states it: it grows with the random walk; zeros without "
                      "drift"),
    "base_pose": Topic("sensor/base_pose", "geometry_msgs/msg/PoseStamped",
                       "rover base (x forward, y left, z up) in frame `map`"),
    **{f"hazcam_{end}": Topic(f"sensor/hazcam_{end}/depth", "sensor_msgs/msg/Image",
                              f"the {end} hazard camera's depth (32FC1, REP 117, frame "
                              f"`hazcam_{end}_optical`; its pose: `base_pose` and the "
                              f"`--hazcam` mounting); 0 x 0 on the flyer, which has none")
       for end in ("front", "rear")},
    **{f"hazcam_{end}_info": Topic(f"sensor/hazcam_{end}/camera_info",
                                   "sensor_msgs/msg/CameraInfo",
                                   f"the {end} hazard camera's intrinsics")
       for end in ("front", "rear")},
    "surface": Topic("map/surface", CLOUD_UPDATE,
                     "accumulated observed surface S_t, incremental: float32 `x, y, z`; uint16 "
                     "`views` (frames that saw the voxel)", incremental=True),
    "predicted": Topic("map/occupancy/predicted", CLOUD_UPDATE,
                       "learned prediction O_hat_t, incremental: voxel centres (0.4 m) at "
                       "probability >= 0.5 with no depth return in them yet; float32 `x, y, z, "
                       "probability`. Empty in conditions that do not use it",
                       incremental=True),
    "planner_map": Topic("map/occupancy/planner", CLOUD_UPDATE,
                         "planner-facing occupancy, incremental: float32 `x, y, z`; uint8 "
                         "`source`; uint16 `views`; uint8 `channels` (1: gain, 2: collision "
                         "checking; 3 but under gated-split)", incremental=True),
    "path": Topic("plan/path", "nav_msgs/msg/Path",
                  "rover base poses of the next motion; the first is the current pose"),
    "rejected": Topic("plan/rejected", "nav_msgs/msg/Path",
                      "goal base poses of the candidate motions the planner tried and found "
                      "infeasible this step, in the order tried (evaluation of its decisions)"),
    "traversability": Topic("map/traversability", "nav_msgs/msg/OccupancyGrid",
                            "the rover's traversability map around it (from observed returns "
                            "only: -1 unknown, 0 clear, 100 an obstacle to the body), "
                            "0.1 m cells; 0 x 0 on the flyer"),
    "traverse": Topic("plan/traverse", "rovergate_msgs/msg/TraverseReport",
                      "what the traversability layer refused this step, by hazard, the "
                      "planner's choice (best-feasible, rotate, escape, backout, stay), and "
                      "the map points the gain of its chosen view counts (`gain_points`)"),
    "execution": Topic("state/execution", "rovergate_msgs/msg/ExecutionReport",
                       "what the simulator executed: collided, collision samples, minimum "
                       "clearance, length driven"),
    "status": Topic("mission/status", "rovergate_msgs/msg/MissionStatus",
                    "the mission clock: step, steps_total, state (`running`: the tick of the "
                    "step; `paused`: a keep-alive while the ground holds the rover; `done`, "
                    "`aborted`), condition, coverage, collisions"),
    "timing": Topic("diag/timing", "rovergate_msgs/msg/StepTiming",
                    "per-stage compute time per step, dropped-message count"),
    "truth_surface": Topic("truth/surface_samples", "sensor_msgs/msg/PointCloud2",
                           "ground-truth surface samples, for evaluation only",
                           kind="queryable"),
    "truth_occupancy": Topic("truth/occupancy", "sensor_msgs/msg/PointCloud2",
                             "reference occupied points O*, for the oracle conditions only",
                             kind="queryable"),
    "downlink": Topic("downlink", "rovergate_msgs/msg/TelemetryFrame",
                      "telemetry radiated in windows (`seq`, `kind`, `msgtype`, `step`, CDR "
                      "`payload` of a `MissionStatus`, `PoseStamped`, `PointCloud2`, "
                      "`MissionEvent` or `CommandAck`)", network="ground"),
    "downlink_ack": Topic("downlink/ack", "rovergate_msgs/msg/DownlinkAck",
                          "sequence numbers the ground station received", network="ground"),
    "uplink": Topic("uplink", "rovergate_msgs/msg/GroundCommand",
                    "commands (`id`, `verb`, `args`)", network="ground"),
    "uplink_report": Topic("uplink/radiated", "rovergate_msgs/msg/CommandAck",
                           "the ground transmitter's report that it radiated a command "
                           "(`state` radiated, `step`: the link step, `received_s`: when it "
                           "reaches the rover); a ground-side report, so no light time",
                           network="ground"),
}


@dataclass(frozen=True)
class Input:
    """One input of a module: ``lag=1`` means step t needs the message of step t-1."""

    topic: str
    lag: int = 0


@dataclass(frozen=True)
class Module:
    """One node of the graph: a module process of the rover (or the mission manager)."""

    name: str
    doc: str
    inputs: dict[str, Input]
    """The module's inputs by the name its logic reads them under."""
    outputs: tuple[str, ...]
    """Topics it publishes, in the order it publishes them in a step."""
    stages: tuple[str, ...] = ()
    """Timing stages it reports on ``timing`` (a stage per piece of work)."""
    replay: tuple[str, ...] = ()
    """Inputs (names from ``inputs``) whose every past step a restarted module replays to
    rebuild its state; empty for a module that keeps no state between steps."""
    serves: tuple[str, ...] = ()
    """Queryables it answers."""
    asks: tuple[str, ...] = ()
    """Queryables it may ask (the gate asks for truth in the oracle conditions only)."""
    reads: tuple[str, ...] = ()
    """The mission settings (top-level fields and sections of the config) it is built from:
    a change of one of them in flight restarts it (:mod:`mission.link.operations`)."""
    last_step_offset: int = 0
    """The last step it handles is ``steps + last_step_offset`` (the gate and the planner
    have nothing to do after the last pose)."""
    launched: bool = True
    """A module process that ``rovergate run`` starts (the mission is the launcher itself)."""
    progress: str = field(init=False)
    """The output that marks a step as handled: the last one it publishes."""

    def __post_init__(self) -> None:
        object.__setattr__(self, "progress", self.outputs[-1] if self.outputs else "")

    def last_step(self, steps: int) -> int:
        return steps + self.last_step_offset

    def missing(self, step: int, buffers: dict[str, dict[int, Any]]) -> list[str]:
        """The lockstep rule, for both transports: the inputs of ``step`` not yet in
        ``buffers`` (input name -> {step: value}); an input of lag L has none before step L."""
        return [n for n, i in self.inputs.items()
                if step - i.lag >= 0 and step - i.lag not in buffers[n]]

    def take(self, step: int, buffers: dict[str, dict[int, Any]]) -> dict[str, Any]:
        """Remove and return the inputs of ``step`` from ``buffers`` (None where absent)."""
        return {n: buffers[n].pop(step - i.lag, None) for n, i in self.inputs.items()}


#: The modules, in launch order; the mission last.
MODULES: dict[str, Module] = {m.name: m for m in [
    Module("sim", "the simulator: drives the path of step t-1, renders step t, serves truth",
           inputs={"tick": Input("status"), "path": Input("path", lag=1)},
           outputs=("execution", "depth", "camera_info", "pose", "pose_cov", "hazcam_front",
                    "hazcam_front_info", "hazcam_rear", "hazcam_rear_info", "base_pose"),
           stages=("execute", "render"), replay=("path",),
           serves=("truth_surface", "truth_occupancy"),
           reads=("scene", "platform", "start", "seed", "sensor", "sensing", "rover", "flyer",
                  "eval", "mapper", "hazcam")),
    Module("mapper", "the mapper: depth into S_t, and the learned prediction",
           inputs={"depth": Input("depth"), "info": Input("camera_info"),
                   "pose": Input("pose"), "front": Input("hazcam_front"),
                   "rear": Input("hazcam_rear"), "base": Input("base_pose")},
           outputs=("surface", "predicted"), stages=("integrate",),
           replay=("depth", "info", "pose", "front", "rear", "base"),
           reads=("condition", "scene", "mapper", "hazcam", "platform")),
    Module("gate", "the gate: the planner-facing occupancy of the mission's condition",
           inputs={"surface": Input("surface"), "predicted": Input("predicted"),
                   "pose": Input("pose_cov"), "info": Input("camera_info"),
                   "depth": Input("depth")},
           outputs=("planner_map",), stages=("gate",), replay=("pose", "info", "depth"),
           asks=("truth_occupancy",),
           reads=("condition", "scene", "gate", "sensor", "mapper"),
           last_step_offset=-1),
    Module("planner", "the planner: the next motion from the planner-facing map, checked on "
           "the rover's traversability layer",
           inputs={"map": Input("planner_map"), "base": Input("base_pose"),
                   "depth": Input("depth"), "pose": Input("pose"),
                   "info": Input("camera_info"), "front": Input("hazcam_front"),
                   "rear": Input("hazcam_rear"), "execution": Input("execution", lag=1),
                   "path": Input("path", lag=1)},
           outputs=("traversability", "traverse", "rejected", "path"),
           stages=("traverse", "plan"),
           replay=("base", "depth", "pose", "info", "front", "rear", "execution", "path"),
           reads=("scene", "platform", "seed", "sensor", "rover", "flyer", "planner", "mapper",
                  "hazcam", "traverse"),
           last_step_offset=-1),
    Module("mission", "the mission manager: the clock, coverage, the record, the ground link",
           inputs={"path": Input("path", lag=1), "rejected": Input("rejected", lag=1),
                   "execution": Input("execution", lag=1),
                   "traverse": Input("traverse", lag=1),
                   "predicted": Input("predicted", lag=1),
                   "planner_map": Input("planner_map", lag=1),
                   "surface": Input("surface"), "base": Input("base_pose")},
           outputs=("status",), asks=("truth_surface",), launched=False),
]}

#: The module processes ``rovergate run`` starts, in launch order.
LAUNCHED: tuple[str, ...] = tuple(m.name for m in MODULES.values() if m.launched)


def stage_module() -> dict[str, str]:
    """Which module reports each timing stage."""
    return {stage: m.name for m in MODULES.values() for stage in m.stages}


def readers(setting: str) -> tuple[str, ...]:
    """The launched modules built from mission setting ``setting`` (a top-level config field
    or section): what restarts when it changes in flight."""
    return tuple(m.name for m in MODULES.values() if m.launched and setting in m.reads)


def journal_topics() -> tuple[frozenset[str], frozenset[str]]:
    """The topics the mission journals for a restarted module: ``(every_step, last_steps)``.

    Every step of what some module replays, and of the clock (the ticks); the last few steps
    of every other input, which a restarted module needs only from the step it resumes at.
    """
    every = {"status"} | {m.inputs[n].topic for m in MODULES.values() for n in m.replay}
    inputs = {i.topic for m in MODULES.values() if m.launched for i in m.inputs.values()}
    return frozenset(every), frozenset(inputs - every)


def consumers(topic: str) -> list[tuple[str, str, int]]:
    """``(module, input name, lag)`` of every input that reads ``topic``."""
    return [(m.name, name, i.lag) for m in MODULES.values() for name, i in m.inputs.items()
            if i.topic == topic]


def producer(topic: str) -> str | None:
    """The module that publishes or serves ``topic`` (None: the ground station)."""
    for m in MODULES.values():
        if topic in m.outputs or topic in m.serves:
            return m.name
    return None


def check_graph() -> None:
    """Raise ValueError when the declaration is inconsistent (a test runs it; so does every
    import of :mod:`rovergate.keys`)."""
    for m in MODULES.values():
        for name, i in m.inputs.items():
            if i.topic not in TOPICS:
                raise ValueError(f"module {m.name}: input {name} reads unknown topic {i.topic}")
            if producer(i.topic) is None:
                raise ValueError(f"module {m.name}: nothing publishes {i.topic}")
        for t in (*m.outputs, *m.serves, *m.asks):
            if t not in TOPICS:
                raise ValueError(f"module {m.name}: unknown topic {t}")
        for r in m.replay:
            if r not in m.inputs:
                raise ValueError(f"module {m.name}: replays {r}, which is not an input")
    for name, topic in TOPICS.items():
        if topic.network == "rover" and producer(name) is None and name != "timing":
            raise ValueError(f"topic {name} has no producer in the graph")


#: Topics that cross the graph's edge (every module's timing; the ground link): their ends.
_EDGE: dict[str, tuple[str, str]] = {
    "timing": ("every module", "mission"), "downlink": ("mission", "ground station"),
    "downlink_ack": ("ground station", "mission"), "uplink": ("ground station", "mission"),
    "uplink_report": ("ground transmitter (the mission's bridge)", "ground station")}


def topic_table(namespace: str = "rover", ground_namespace: str = "ground") -> str:
    """The topic table of docs/architecture.md (markdown), generated from :data:`TOPICS` and
    :data:`MODULES`."""
    rows = ["| key | type | from → to | what |", "|---|---|---|---|"]
    for name, t in TOPICS.items():
        ns = namespace if t.network == "rover" else ground_namespace
        kind = " (queryable)" if t.kind == "queryable" else ""
        if name in _EDGE:
            src, dst = _EDGE[name]
        else:
            src = producer(name) or "?"
            dst = ", ".join(sorted({m for m, _, _ in consumers(name)}
                                   | {m.name for m in MODULES.values() if name in m.asks}))
        rows.append(f"| `{ns}/{t.suffix}` | `{t.msgtype}`{kind} | {src} → {dst} | {t.doc} |")
    rows.append(f"| `{namespace}/alive/<module>` | liveliness token | each module | "
                f"{', '.join(f'`{m}`' for m in MODULES)}: declared once the module is ready |")
    rows.append(f"| `{namespace}/mission/journal/<key>` | queryable | mission → a restarted "
                "module | the samples of past steps it replays (`?from=A;to=B`, steps "
                "inclusive) |")
    rows.append(f"| `{ground_namespace}/alive/rover`, `{ground_namespace}/alive/station` | "
                "liveliness token | mission, ground station | the two ends of the ground link |")
    return "\n".join(rows)


check_graph()

if __name__ == "__main__":
    print(topic_table())
