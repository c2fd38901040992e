"""``rovergate replay OUT/bag``: a recorded mission, published again over Zenoh.

Every message of the bag goes out on the key it was recorded from (its ROS 2 topic without
the leading ``/``, e.g. ``rover/map/occupancy/planner``), as the same CDR bytes with the
encoding the mission used (``application/cdr`` and the ROS 2 type as schema), in the order
and at the pace it was recorded, times ``--speed`` (0: as fast as it can). So any subscriber
of a live mission (``examples/remote_subscriber.py``, the live view) watches a past one. The
bag may be any rosbag2 bag of CDR messages (MCAP or SQLite storage), a study run's included.

The replay is a Zenoh peer; subscribers connect to its ``--listen`` endpoint (or it connects
to theirs, or to a router, with ``--connect``). As on a live mission, a link from another
machine may only subscribe (:func:`rovergate.access.rover_network`). ``--viz`` and ``--ros2``
serve it to Foxglove and to the ROS 2 graph as ``rovergate run`` does.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import tyro

from rovergate.config import SessionConfig
from rovergate.errors import ConfigError

log = logging.getLogger("rovergate.replay")


@dataclass
class ReplayConfig:
    """Publish a recorded mission (a rosbag2 bag) again over Zenoh, on the keys it was
    recorded from."""

    bag: tyro.conf.Positional[Path]
    """The bag's directory: OUT/bag of a mission (or OUT/runs/<id>/bag of a study run given
    --record)."""
    speed: float = 1.0
    """Pace relative to the recording (2: twice as fast); 0 publishes as fast as it can."""
    wait_subscriber_s: float = 60.0
    """Before the first message, wait up to this many seconds for a subscriber to any of the
    bag's keys, a Foxglove client's subscription with --viz, or a ROS 2 subscriber with
    --ros2, and fail if none comes (0: start at once; what no one subscribes to yet is lost,
    as on a live mission)."""
    topics: tuple[str, ...] = ()
    """Only these ROS 2 topics (e.g. /rover/map/occupancy/planner); empty: all."""
    viz: bool = False
    """Serve the replay to Foxglove too (as `rovergate run --viz`), with the scene's mesh
    when the mission's config.json lies beside the bag."""
    viz_host: str = "127.0.0.1"
    """Address the live view listens on."""
    viz_port: int = 8765
    """Port of the live view (0: any free one; the log says which)."""
    ros2: bool = False
    """Publish the replay into the ROS 2 graph too (as `rovergate run --ros2`)."""
    ros2_router: str = "tcp/localhost:7447"
    """The ROS 2 Zenoh router (rmw_zenohd) to join."""
    ros2_domain: int = 0
    """The ROS domain id to publish in."""
    session: tyro.conf.OmitArgPrefixes[SessionConfig] = field(
        default_factory=lambda: SessionConfig(namespace=""))
    """Where subscribers reach the replay over Zenoh: --listen tcp/127.0.0.1:7447 (they
    connect to it) or --connect ENDPOINT (a router, or a subscriber's listener); with
    neither, only --viz and --ros2 get it. --namespace publishes under another namespace than
    the recorded one (the first segment of every key), e.g. to replay beside a live mission;
    empty: the recorded one."""


@dataclass
class ReplayStats:
    messages: int = 0
    bytes: int = 0
    wall_s: float = 0.0
    recorded_s: float = 0.0


def open_bag(path: Path):
    """An opened rosbags reader of ``path``, or ConfigError saying what is wrong with it."""
    from rosbags.rosbag2 import Reader
    path = Path(path)
    if not path.is_dir():
        raise ConfigError(f"{path} is not a bag directory; give the bag of a mission, "
                          "e.g. `rovergate replay runs/latest/bag`")
    if not (path / "metadata.yaml").is_file():
        raise ConfigError(f"{path} has no metadata.yaml: its mission's manager was stopped "
                          "before it closed the bag (its .mcap holds the finished chunks, "
                          "which MCAP's streaming readers read); replay needs a closed bag")
    try:
        reader = Reader(path)
        reader.open()
    except Exception as exc:
        raise ConfigError(f"{path}: not a readable rosbag2 bag ({exc})") from None
    return reader


def key_of(topic: str, namespace: str = "") -> str:
    """The Zenoh key a ROS 2 topic was recorded from, under ``namespace`` if given."""
    key = topic.lstrip("/")
    if namespace:
        key = f"{namespace}/{key.split('/', 1)[1]}" if "/" in key else f"{namespace}/{key}"
    return key


def replay(cfg: ReplayConfig, taps=None) -> ReplayStats:
    """Publish the bag as configured; ``taps`` (:class:`rovergate.taps.Taps`: the live view)
    get every message too, under its graph topic name where it has one."""
    import zenoh

    from rovergate.access import rover_network
    from rovergate.graph import TOPICS
    from rovergate.module import STOP
    from rovergate.session import open_session

    if cfg.speed < 0:
        raise ConfigError(f"--speed must be at least 0 (0: as fast as it can), got {cfg.speed}")
    reader = open_bag(cfg.bag)
    if not (cfg.session.listen or cfg.session.connect or taps):
        reader.close()
        raise ConfigError("the replay would reach no one: give --listen tcp/127.0.0.1:7447 "
                          "(subscribers connect there), --connect ENDPOINT, --viz or --ros2")
    try:
        connections = [c for c in reader.connections
                       if not cfg.topics or c.topic in cfg.topics]
        unknown = sorted(set(cfg.topics) - {c.topic for c in reader.connections})
        if unknown:
            raise ConfigError(f"--topics: {', '.join(unknown)} not in {cfg.bag}; it holds "
                              f"{', '.join(sorted({c.topic for c in reader.connections}))}")
        bad = [c.topic for c in connections if c.ext.serialization_format != "cdr"]
        if bad:
            raise ConfigError(f"{cfg.bag}: {', '.join(bad)} not serialised as CDR")
        namespace = cfg.session.namespace or _recorded_namespace(connections)
        session = open_session(dataclasses.replace(cfg.session, wait_for_peers=0),
                               rover_network(namespace))
        # Which graph topic each connection is (the live view names channels by it).
        by_suffix = {t.suffix: name for name, t in TOPICS.items()}
        names = {c.id: by_suffix.get(key_of(c.topic).split("/", 1)[-1]) for c in connections}
        # ...where its type is the topic's (a bag of an older version sent the maps whole,
        # as PointCloud2: Zenoh subscribers get them, the live view and ROS 2 do not).
        names = {i: n if n and TOPICS[n].msgtype == c.msgtype else None
                 for (i, n), c in zip(names.items(), connections, strict=True)}
        publishers = {
            c.id: session.declare_publisher(
                key_of(c.topic, cfg.session.namespace),
                encoding=zenoh.Encoding.APPLICATION_CDR.with_schema(c.msgtype),
                congestion_control=zenoh.CongestionControl.BLOCK)
            for c in connections}
        try:
            log.info("replaying %s (%d messages on %d topics) at speed %s; Zenoh: %s",
                     cfg.bag, sum(c.msgcount for c in connections), len(connections),
                     cfg.speed or "max",
                     f"subscribers connect to {', '.join(cfg.session.listen)}"
                     if cfg.session.listen else f"connected to {', '.join(cfg.session.connect)}"
                     if cfg.session.connect else "no endpoint (the live view, ROS 2 only)")
            viewers = [t.watched for t in (taps.taps if taps else []) if hasattr(t, "watched")]
            _await_subscriber(list(publishers.values()), viewers, cfg.wait_subscriber_s, STOP)
            stats = ReplayStats()
            t_wall = time.monotonic()
            t_first: int | None = None
            for conn, t_ns, data in reader.messages(connections=connections):
                if STOP.is_set():
                    break
                t_first = t_ns if t_first is None else t_first
                if cfg.speed > 0:
                    due = t_wall + (t_ns - t_first) / 1e9 / cfg.speed
                    STOP.wait(max(0.0, due - time.monotonic()))  # pacing, not a wait on others
                publishers[conn.id].put(data)
                if taps and names[conn.id]:
                    taps.put(names[conn.id], bytes(data), t_ns)
                stats.messages += 1
                stats.bytes += len(data)
                stats.recorded_s = (t_ns - t_first) / 1e9
            stats.wall_s = time.monotonic() - t_wall
        finally:
            for p in publishers.values():
                p.undeclare()
            session.close()
    finally:
        reader.close()
    log.info("replayed %d messages (%.1f MB) of %.3f s of recording in %.3f s", stats.messages,
             stats.bytes / 1e6, stats.recorded_s, stats.wall_s)
    return stats


def _recorded_namespace(connections) -> str:
    names = {c.topic.lstrip("/").split("/", 1)[0] for c in connections}
    return names.pop() if len(names) == 1 else "rover"


def _await_subscriber(publishers, viewers, timeout_s: float, stop) -> None:
    """Wait for a Zenoh subscriber of a publisher, or a tap that is watched (a Foxglove
    client's subscription, a ROS 2 subscriber)."""
    if timeout_s <= 0:
        log.info("starting at once (--wait-subscriber-s 0): a subscriber that comes later "
                 "misses what was sent before it")
        return
    log.info("waiting up to %.0f s for a subscriber before the first message "
             "(--wait-subscriber-s 0 starts at once)", timeout_s)
    deadline = time.monotonic() + timeout_s
    while not (any(p.matching_status.matching for p in publishers)
               or any(watched() for watched in viewers)):
        if time.monotonic() > deadline:
            raise ConfigError(f"no subscriber within {timeout_s:.0f} s (--wait-subscriber-s): "
                              "none connected to the replay's --listen endpoint, opened the "
                              "live view or subscribed from ROS 2")
        if stop.wait(0.05):
            return


def live_view(cfg: ReplayConfig, load_scene: Callable[[Any], Any] | None = None):
    """The live view of a replay (``--viz``), showing the recorded mission's scene when its
    ``config.json`` lies beside the bag and the caller gave ``load_scene`` (a
    ``SceneConfig`` -> scene function: the composition root gives
    :func:`rover_sim.catalog.load_scene`)."""
    from ecosystem.live_view import LiveView
    from rovergate.config import load_config
    scene = None
    saved = Path(cfg.bag).resolve().parent / "config.json"
    if saved.is_file() and load_scene is not None:
        try:
            mission = load_config(saved)
            scene = load_scene(mission.scene)
        except Exception as exc:  # the view goes on without the mesh
            log.warning("no scene mesh in the live view: %s does not load (%s)", saved, exc)
    return LiveView(cfg.viz_host, cfg.viz_port, _bag_namespace(cfg), scene)


def _bag_namespace(cfg: ReplayConfig) -> str:
    """The namespace the replay publishes under: --namespace, else the recorded one."""
    if cfg.session.namespace:
        return cfg.session.namespace
    reader = open_bag(cfg.bag)
    try:
        return _recorded_namespace(reader.connections)
    finally:
        reader.close()


def main(cfg: ReplayConfig, load_scene: Callable[[Any], Any] | None = None) -> int:
    """Replay the bag of ``cfg``; ``load_scene`` as in :func:`live_view`."""
    from rovergate.logs import init_logging
    from rovergate.taps import Taps
    init_logging("replay")
    taps = Taps([live_view(cfg, load_scene)] if cfg.viz else [])
    try:
        if cfg.ros2:
            from ecosystem.ros2 import Ros2Bridge
            taps.taps.append(Ros2Bridge(cfg.ros2_router, cfg.ros2_domain,
                                        _bag_namespace(cfg), hold=True))
        replay(cfg, taps)
    finally:
        taps.close()
    return 0
