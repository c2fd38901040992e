"""The flight recorder's writer: the bag, written with rosbags (:class:`BagFile`), on the
recorder's thread or in a process of its own.

``python -m ecosystem.bag_writer DIRECTORY NAMESPACE COMPRESSION`` (the recorder,
:class:`ecosystem.recorder.FlightRecorder`, starts it for an in-process mission) reads frames
from its standard input,
each a little-endian header (uint32 index of the topic in
:func:`rovergate.taps.tapped_topics`, uint64 log time in ns, uint64 payload length) and the
payload, writes each as a message of a rosbag2 bag with MCAP storage, and when its input ends
closes the bag and prints what it wrote as one JSON line on standard output.

Its own process, at the lowest priority, because rosbags' writer copies every payload several
times while it holds Python's lock, which an in-process mission's loop needs. The input ends
when the mission closes it, or when the mission's process dies in any way: the bag is closed
either way. It ignores Ctrl-C (the mission ends it).
"""

from __future__ import annotations

import contextlib
import json
import os
import signal
import struct
import sys
import time
from collections import Counter
from pathlib import Path

HEADER = struct.Struct("<IQQ")


def _read_exact(stream, n: int) -> bytes | None:
    """``n`` bytes, or None at the end of the input (a cut frame is the end too)."""
    data = stream.read(n)
    return data if data is not None and len(data) == n else None


def connections(namespace: str) -> list[dict[str, str]]:
    """The bag's connections, one per tapped topic in :func:`rovergate.taps.tapped_topics`'s
    order: its graph name, ROS 2 topic, type, ``ros2msg`` definition and RIHS01 hash (the
    writer process is given them, so that it never builds the type store)."""
    from rovergate.graph import TOPICS
    from rovergate.keys import Keys
    from rovergate.messages import TYPESTORE
    from rovergate.taps import tapped_topics
    keys = Keys(namespace)
    out = []
    for t in tapped_topics():
        msgtype = TOPICS[t].msgtype
        out.append({"name": t, "topic": "/" + keys.key(t), "msgtype": msgtype,
                    "msgdef": TYPESTORE.generate_msgdef(msgtype, ros_version=2)[0],
                    "rihs01": TYPESTORE.hash_rihs01(msgtype)})
    return out


class BagFile:
    """A rosbag2 bag with MCAP storage of the given connections (:func:`connections`),
    written with rosbags: what both of the recorder's writers (its thread, or this module's
    process) write through."""

    def __init__(self, directory: Path, specs: list[dict[str, str]], compression: str) -> None:
        from rosbags.rosbag2 import StoragePlugin, Writer
        from rosbags.rosbag2.enums import CompressionFormat, CompressionMode

        self.directory = Path(directory)
        self.topics = [c["name"] for c in specs]
        self._writer = Writer(self.directory, version=9, storage_plugin=StoragePlugin.MCAP)
        if compression == "zstd":
            self._writer.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)
        self._writer.open()
        self._connections = [self._writer.add_connection(c["topic"], c["msgtype"],
                                                         msgdef=c["msgdef"], rihs01=c["rihs01"])
                             for c in specs]
        self.counts: Counter[str] = Counter()
        self.payload_bytes = 0
        self.write_s = 0.0
        self.error: str | None = None

    def write(self, index: int, time_ns: int, payload: bytes) -> None:
        """One message; after a failure, nothing more (the error says why)."""
        if self.error is not None or not 0 <= index < len(self.topics):
            return
        t0 = time.perf_counter()
        try:
            self._writer.write(self._connections[index], time_ns, payload)
        except Exception as exc:
            self.error = f"{type(exc).__name__}: {exc}"
            return
        self.write_s += time.perf_counter() - t0
        self.counts[self.topics[index]] += 1
        self.payload_bytes += len(payload)

    def close(self) -> dict:
        """Write the bag's summary and metadata.yaml; what it holds (JSON-ready)."""
        t0 = time.perf_counter()
        try:
            self._writer.close()
        except Exception as exc:
            self.error = self.error or f"{type(exc).__name__}: {exc}"
        self.write_s += time.perf_counter() - t0
        file_bytes = sum(p.stat().st_size for p in self.directory.iterdir() if p.is_file())
        return {"messages": {t: self.counts[t] for t in self.topics},
                "payload_bytes": self.payload_bytes, "file_bytes": file_bytes,
                "write_s": self.write_s, "error": self.error}


def main(argv: list[str]) -> int:
    directory, compression = Path(argv[0]), argv[1]
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    with contextlib.suppress(OSError):
        os.setpriority(os.PRIO_PROCESS, 0, 19)
    stream = sys.stdin.buffer
    bag = BagFile(directory, json.loads(stream.readline()), compression)
    while (header := _read_exact(stream, HEADER.size)) is not None:
        index, time_ns, length = HEADER.unpack(header)
        payload = _read_exact(stream, length)
        if payload is None:
            break
        bag.write(index, time_ns, payload)  # after a failure it reads on: no full pipe
    summary = bag.close()
    with contextlib.suppress(BrokenPipeError):  # the mission may be gone: the bag is closed
        print(json.dumps(summary), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
