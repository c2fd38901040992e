"""The flight recorder's writer: a process of its own that writes the bag with rosbags.

``python -m ecosystem.bag_writer DIRECTORY NAMESPACE COMPRESSION`` (the recorder,
:class:`ecosystem.recorder.FlightRecorder`, starts it) reads frames from its standard input,
each a little-endian header (uint32 index of the topic in
:func:`ecosystem.taps.tapped_topics`, uint64 log time in ns, uint64 payload length) and the
payload, writes each as a message of a rosbag2 bag with MCAP storage, and when its input ends
closes the bag and prints what it wrote as one JSON line on standard output.

Its own process, at the lowest priority, because rosbags' writer copies every payload several
times while it holds Python's lock: in the mission's process that took the loop's time. The
input ends when the mission closes it, or when the mission's process dies in any way: the bag
is closed either way. It ignores Ctrl-C (the mission ends it).
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


def main(argv: list[str]) -> int:
    directory, namespace, compression = Path(argv[0]), argv[1], argv[2]
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    with contextlib.suppress(OSError):
        os.setpriority(os.PRIO_PROCESS, 0, 19)
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.rosbag2.enums import CompressionFormat, CompressionMode

    from ecosystem.taps import tapped_topics
    from rovergate.graph import TOPICS
    from rovergate.keys import Keys
    from rovergate.messages import TYPESTORE

    topics = tapped_topics()
    keys = Keys(namespace)
    writer = Writer(directory, version=9, storage_plugin=StoragePlugin.MCAP)
    if compression == "zstd":
        writer.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)
    writer.open()
    connections = [writer.add_connection("/" + keys.key(t), TOPICS[t].msgtype,
                                         typestore=TYPESTORE) for t in topics]
    counts: Counter[str] = Counter()
    payload_bytes = 0
    write_s = 0.0
    error = None
    stream = sys.stdin.buffer
    while (header := _read_exact(stream, HEADER.size)) is not None:
        index, time_ns, length = HEADER.unpack(header)
        payload = _read_exact(stream, length)
        if payload is None:
            break
        if error is not None or index >= len(topics):
            continue  # failed: read on, so that the mission never waits on a full pipe
        t0 = time.perf_counter()
        try:
            writer.write(connections[index], time_ns, payload)
        except Exception as exc:
            error = f"{type(exc).__name__}: {exc}"
            continue
        write_s += time.perf_counter() - t0
        counts[topics[index]] += 1
        payload_bytes += length
    t0 = time.perf_counter()
    try:
        writer.close()
    except Exception as exc:
        error = error or f"{type(exc).__name__}: {exc}"
    write_s += time.perf_counter() - t0
    file_bytes = sum(p.stat().st_size for p in directory.iterdir() if p.is_file())
    with contextlib.suppress(BrokenPipeError):  # the mission may be gone: the bag is closed
        print(json.dumps({"messages": {t: counts[t] for t in topics},
                          "payload_bytes": payload_bytes, "file_bytes": file_bytes,
                          "write_s": write_s, "error": error}), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
