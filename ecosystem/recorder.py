"""The flight recorder: every message the mission's modules publish, into a rosbag2 bag.

The bag is ``OUT/bag/``: ``bag.mcap`` (MCAP storage; its chunks compressed with zstd if
``--record-compression zstd``) and rosbag2's ``metadata.yaml`` (version 9, ``ros_distro:
jazzy``), written with rosbags' ``rosbag2.Writer`` and what rosbags leaves out of rosbag2's own
writing added (:mod:`ecosystem.bag_writer`: CRCs, each channel's ``topic_type_hash``). Each
topic is a connection named as its ROS 2 topic (``/`` + its Zenoh key, e.g.
``/rover/map/occupancy/planner``), with the type's ``ros2msg`` definition as schema and its
RIHS01 type hash, and the CDR payloads as they travelled (the process set) or as the process
set would send them (``--in-process``). A message's log time is when the recorder received it
(wall clock, ns); its header stamp is the planning step (:mod:`rovergate.messages`).

The transport hands a payload over and goes on; a thread of the recorder writes it (the
process set: the mission manager's own thread mostly waits) or sends it down a pipe to a
writer process (in process: rosbags' copies would hold the Python lock the loop needs), at
the lowest priority either way (:mod:`ecosystem.bag_writer`). Any MCAP reader opens the bag
(``mcap`` with ``mcap-ros2-support``, Foxglove, ``ros2 bag`` of Jazzy or later with the MCAP
plugin); ``rovergate replay OUT/bag`` publishes it again over Zenoh.

The writer process closes the bag when its input ends, which it does when the mission's
process dies in any way too. A process-set mission's manager killed outright leaves a bag
without its summary and ``metadata.yaml`` (MCAP's streaming readers read its finished
chunks); its ``--resume`` records into ``OUT/bag.2`` (and so on), beside the first.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import queue
import shutil
import subprocess
import sys
import threading
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

from ecosystem.bag_writer import HEADER, BagFile, connections
from rovergate.taps import Payload, tapped_topics

log = logging.getLogger("rovergate.recorder")

BAG = "bag"
"""The bag's directory under a mission's ``--out``."""
CLOSE_TIMEOUT_S = 120.0
"""How long the writer may take to write what is pending and close the bag."""
MAX_PENDING_BYTES = 1 << 30
"""Payload the writer may fall behind by; past it a message is dropped and counted rather
than the mission's memory grown without bound (a disk far slower than the mission)."""

Compression = Literal["zstd", "none"]
Writer = Literal["thread", "process"]


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
    """Seconds the writer process spent writing (compression included)."""
    compression: str = "none"
    writer: str = "thread"
    """Where the bag was written: the recorder's thread (the process set's mission manager)
    or a process of its own (an in-process mission)."""
    dropped: int = 0
    """Messages not recorded because the writer fell more than MAX_PENDING_BYTES behind."""
    error: str | None = None
    """Why the recording stopped early (a full disk, ...); None when it is complete."""


class FlightRecorder:
    """A :class:`rovergate.taps.Tap` that records every message into a rosbag2 MCAP bag.

    The transport's side only queues each payload; a thread of the recorder takes it from
    there. With ``writer="thread"`` that thread writes the bag itself (the process set's
    mission manager, whose own thread mostly waits); with ``writer="process"`` it hands the
    bytes down a pipe to :mod:`ecosystem.bag_writer`'s process (an in-process mission, whose
    loop needs Python's lock that rosbags' copies would hold)."""

    def __init__(self, directory: Path, namespace: str = "rover",
                 compression: Compression = "none", writer: Writer = "thread") -> None:
        if compression not in ("zstd", "none"):
            raise ValueError(f"record compression {compression!r}: choose zstd or none")
        if writer not in ("thread", "process"):
            raise ValueError(f"writer {writer!r}: choose thread or process")
        self.directory = Path(directory)
        self.directory.parent.mkdir(parents=True, exist_ok=True)
        if self.directory.exists():
            raise FileExistsError(f"{self.directory} exists; a bag is written only once")
        self._topics = tapped_topics()
        self._index = {t: i for i, t in enumerate(self._topics)}
        self._bag: BagFile | None = None
        self._proc: subprocess.Popen | None = None
        specs = connections(namespace)
        if writer == "thread":
            self._bag = BagFile(self.directory, specs, compression)
        else:
            # Its own process group, so that a Ctrl-C to the mission's terminal does not
            # reach it (the mission ends it), but the mission's session: Linux schedules a
            # session as a group (autogroup), and in a session of its own the writer's low
            # priority would count for nothing against the mission.
            self._proc = subprocess.Popen(
                [sys.executable, "-m", "ecosystem.bag_writer", str(self.directory),
                 compression], stdin=subprocess.PIPE, stdout=subprocess.PIPE, process_group=0)
            self._proc.stdin.write(json.dumps(specs).encode() + b"\n")
        self.stats = RecordStats(str(self.directory), compression=compression, writer=writer)
        self._queue: queue.SimpleQueue[tuple[int, Payload, int] | threading.Event | None] = \
            queue.SimpleQueue()
        self._error: str | None = None
        self._closed = False
        self._pending = 0
        self._lock = threading.Lock()
        self._thread = threading.Thread(target=self._send, name="flight-recorder", daemon=True)
        self._thread.start()

    def put(self, topic: str, payload: Payload, time_ns: int) -> None:
        if self._error is not None:
            raise RuntimeError(f"the flight recorder stopped: {self._error}")
        index = self._index.get(topic)
        if index is None:
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
        self._queue.put((index, payload, time_ns))

    def _send(self) -> None:
        if self._bag is not None:
            # The lowest priority for this thread alone (Linux: a thread id is a process id
            # to setpriority): it takes the CPU the loop leaves idle, not the loop's.
            with contextlib.suppress(OSError, AttributeError):
                os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), 19)
        while (item := self._queue.get()) is not None:
            if isinstance(item, threading.Event):
                item.set()  # flush(): everything before it is written or in the pipe
                continue
            index, payload, time_ns = item
            with self._lock:
                self._pending -= len(payload)
            if self._error is not None:
                continue
            try:
                data = bytes(payload)  # a Deferred message is encoded here, off the loop
            except Exception as exc:
                self._error = f"a {self._topics[index]} message did not encode: {exc}"
                log.error("the flight recorder stopped: %s", self._error)
                continue
            if self._bag is not None:
                self._bag.write(index, time_ns, data)
                if self._bag.error is not None:
                    self._error = self._bag.error
                    log.error("the flight recorder cannot write %s: %s", self.directory,
                              self._error)
                continue
            try:  # the pipe's writes release Python's lock: the loop goes on meanwhile
                self._proc.stdin.write(HEADER.pack(index, time_ns, len(data)))
                self._proc.stdin.write(data)
                self._proc.stdin.flush()  # in the pipe, not here: a killed mission loses none
            except OSError as exc:
                self._error = f"the bag writer process ended ({exc})"
                log.error("the flight recorder cannot write %s: %s", self.directory,
                          self._error)
        if self._proc is not None:
            with contextlib.suppress(OSError):
                self._proc.stdin.close()  # the end of the input: the writer closes the bag

    def flush(self, timeout_s: float = 60.0) -> bool:
        """Wait until every message put so far is written (or in the writer process's pipe):
        True, or False when ``timeout_s`` passed first."""
        done = threading.Event()
        self._queue.put(done)
        return done.wait(timeout_s)

    def close(self) -> RecordStats:
        """Write what is pending, the bag's summary and ``metadata.yaml``; what it holds."""
        if self._closed:
            return self.stats
        self._closed = True
        self._queue.put(None)
        self._thread.join()
        written = self._bag.close() if self._bag is not None else self._close_process()
        self.stats.messages = written.get("messages", {})
        self.stats.payload_bytes = written.get("payload_bytes", 0)
        self.stats.file_bytes = written.get("file_bytes", 0)
        self.stats.write_s = written.get("write_s", 0.0)
        error = self._error or written.get("error")
        self.stats.error = error
        log.info("recorded %d messages (%.1f MB of payload, %.1f MB on disk) into %s",
                 sum(self.stats.messages.values()), self.stats.payload_bytes / 1e6,
                 self.stats.file_bytes / 1e6, self.directory)
        if error is not None:
            raise RuntimeError(f"the flight recorder stopped early: {error}")
        return self.stats

    def _close_process(self) -> dict:
        self._proc.stdin = None  # closed by the sender: communicate() only reads
        try:
            out, _ = self._proc.communicate(timeout=CLOSE_TIMEOUT_S)
        except subprocess.TimeoutExpired:
            self._proc.kill()
            out, _ = self._proc.communicate()
            self._error = self._error or (f"the bag writer did not finish within "
                                          f"{CLOSE_TIMEOUT_S:.0f} s")
        try:
            return json.loads(out.decode().strip().splitlines()[-1])
        except (ValueError, IndexError):
            return {"error": f"the bag writer exited with code {self._proc.returncode} and "
                             "no summary"}
