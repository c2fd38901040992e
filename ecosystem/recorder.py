"""The flight recorder: every message the mission's modules publish, into a rosbag2 bag.

The bag is ``OUT/bag/``: ``bag.mcap`` (MCAP storage; its chunks compressed with zstd if
``--record-compression zstd``) and rosbag2's ``metadata.yaml``, written with rosbags'
``rosbag2.Writer``. Each topic is a connection named as its ROS 2 topic (``/`` + its Zenoh key,
e.g. ``/rover/map/occupancy/planner``), with the type's ``ros2msg`` definition as schema and
the CDR payloads as they travelled (the process set) or as the process set would send them
(``--in-process``). A message's log time is when the recorder received it (wall clock, ns);
its header stamp is the planning step (:mod:`rovergate.messages`).

Writing runs on a thread of its own: the transport hands a payload over and goes on. Any
MCAP reader opens the bag (``mcap`` with ``mcap-ros2-support``, Foxglove, ``ros2 bag`` with
the MCAP plugin); ``rovergate replay OUT/bag`` publishes it again over Zenoh.

A mission whose manager is killed leaves a bag without its summary and ``metadata.yaml``;
MCAP's streaming readers still read its finished chunks. A resumed mission records into
``OUT/bag.2`` (and so on), beside the first.
"""

from __future__ import annotations

import contextlib
import logging
import os
import queue
import shutil
import threading
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.rosbag2.enums import CompressionFormat, CompressionMode

from ecosystem.taps import tapped_topics
from rovergate.graph import TOPICS
from rovergate.keys import Keys
from rovergate.messages import TYPESTORE

log = logging.getLogger("rovergate.recorder")

BAG = "bag"
"""The bag's directory under a mission's ``--out``."""
MAX_PENDING_BYTES = 1 << 30
"""Payload the writer may fall behind by; past it a message is dropped and counted rather
than the mission's memory grown without bound (a disk far slower than the mission)."""

Compression = Literal["zstd", "none"]


def ros_topic(keys: Keys, topic: str) -> str:
    """The ROS 2 topic name of a graph topic: ``/`` and its Zenoh key."""
    return "/" + keys.key(topic)


def fresh_bag_dir(out: Path, resumed: bool) -> Path:
    """Where a mission in ``out`` records: ``out/bag``, after removing another mission's bag
    there; a resumed mission keeps what its first manager recorded and takes ``bag.2``,
    ``bag.3``, ... ."""
    first = out / BAG
    if not resumed:
        shutil.rmtree(first, ignore_errors=True)
        for old in out.glob(f"{BAG}.*"):
            shutil.rmtree(old, ignore_errors=True)
        return first
    n = 1
    path = first
    while path.exists():
        n += 1
        path = out / f"{BAG}.{n}"
    return path


@dataclass
class RecordStats:
    """What a recording holds, and what it cost."""

    path: str
    messages: dict[str, int] = field(default_factory=dict)
    payload_bytes: int = 0
    file_bytes: int = 0
    write_s: float = 0.0
    """Seconds the writer thread spent writing (compression included)."""
    compression: str = "none"
    dropped: int = 0
    """Messages not recorded because the writer fell more than MAX_PENDING_BYTES behind."""
    error: str | None = None
    """Why the recording stopped early (a full disk, ...); None when it is complete."""


class FlightRecorder:
    """A :class:`ecosystem.taps.Tap` that writes every message into a rosbag2 MCAP bag."""

    def __init__(self, directory: Path, namespace: str = "rover",
                 compression: Compression = "none") -> None:
        if compression not in ("zstd", "none"):
            raise ValueError(f"record compression {compression!r}: choose zstd or none")
        self.directory = Path(directory)
        self.directory.parent.mkdir(parents=True, exist_ok=True)
        self._writer = Writer(self.directory, version=9, storage_plugin=StoragePlugin.MCAP)
        if compression == "zstd":
            self._writer.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)
        self._writer.open()
        keys = Keys(namespace)
        self._connections = {
            t: self._writer.add_connection(ros_topic(keys, t), TOPICS[t].msgtype,
                                           typestore=TYPESTORE)
            for t in tapped_topics()}
        self.stats = RecordStats(str(self.directory), compression=compression)
        self._counts: Counter[str] = Counter()
        self._queue: queue.SimpleQueue[tuple[str, bytes, int] | None] = queue.SimpleQueue()
        self._error: BaseException | None = None
        self._closed = False
        self._pending = 0
        self._lock = threading.Lock()
        self._thread = threading.Thread(target=self._drain, name="flight-recorder", daemon=True)
        self._thread.start()

    def put(self, topic: str, payload: bytes, time_ns: int) -> None:
        if self._error is not None:
            raise RuntimeError(f"the flight recorder stopped: {self._error}")
        if topic not in self._connections:
            return
        with self._lock:
            if self._pending + len(payload) > MAX_PENDING_BYTES:
                self.stats.dropped += 1
                if self.stats.dropped == 1:
                    log.warning("the flight recorder is %d MB behind: dropping messages "
                                "(counted in metrics.json's recording.dropped)",
                                self._pending >> 20)
                return
            self._pending += len(payload)
        self._queue.put((topic, payload, time_ns))

    def _drain(self) -> None:
        # The lowest priority for this thread alone (Linux: a thread id is a process id to
        # setpriority): the recorder takes the CPU the loop leaves idle, not the loop's.
        with contextlib.suppress(OSError, AttributeError):
            os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), 19)
        while (item := self._queue.get()) is not None:
            topic, payload, time_ns = item
            with self._lock:
                self._pending -= len(payload)
            if self._error is not None:
                continue  # failed: keep draining so that nothing waits on us
            t0 = time.perf_counter()
            try:
                self._writer.write(self._connections[topic], time_ns, payload)
            except BaseException as exc:
                self._error = exc
                log.error("the flight recorder cannot write %s: %s", self.directory, exc)
                continue
            self.stats.write_s += time.perf_counter() - t0
            self._counts[topic] += 1
            self.stats.payload_bytes += len(payload)

    def close(self) -> RecordStats:
        """Write what is pending, the bag's summary and ``metadata.yaml``."""
        if self._closed:
            return self.stats
        self._closed = True
        self._queue.put(None)
        self._thread.join()
        self.stats.messages = {t: self._counts[t] for t in self._connections}
        t0 = time.perf_counter()
        try:
            self._writer.close()
        except Exception as exc:
            self._error = self._error or exc
        self.stats.write_s += time.perf_counter() - t0
        self.stats.file_bytes = sum(p.stat().st_size for p in self.directory.iterdir()
                                    if p.is_file())
        if self._error is not None:
            self.stats.error = f"{type(self._error).__name__}: {self._error}"
        log.info("recorded %d messages (%.1f MB of payload, %.1f MB on disk) into %s",
                 sum(self._counts.values()), self.stats.payload_bytes / 1e6,
                 self.stats.file_bytes / 1e6, self.directory)
        if self._error is not None:
            raise RuntimeError(f"the flight recorder stopped early: {self._error}")
        return self.stats
