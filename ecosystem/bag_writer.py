"""The flight recorder's writer: the bag, written with rosbags (:class:`BagFile`), on the
recorder's thread or in a process of its own.

``python -m ecosystem.bag_writer DIRECTORY COMPRESSION`` (the recorder,
:class:`ecosystem.recorder.FlightRecorder`, starts it for an in-process mission) reads from
its standard input the bag's connections (one JSON line, :func:`connections`), then frames,
each a little-endian header (uint32 index of the topic in
:func:`rovergate.taps.tapped_topics`, uint64 log time in ns, uint64 payload length) and the
payload, writes each as a message of a rosbag2 bag with MCAP storage, and when its input ends
closes the bag and prints what it wrote as one JSON line on standard output.

Its own process, at the lowest priority, because rosbags' writer copies every payload several
times while it holds Python's lock, which an in-process mission's loop needs. The input ends
when the mission closes it, or when the mission's process dies in any way: the bag is closed
either way. It ignores Ctrl-C (the mission ends it).

Where rosbags 0.11's writer leaves out what ``ros2 bag record -s mcap`` on Jazzy writes, the
bag has it (:class:`McapStorage`): the CRC-32 of every chunk, of the data section and of the
summary (rosbags writes 0, "not computed"), every channel's ``topic_type_hash`` (the type's
RIHS01 hash, where rosbag2's MCAP plugin reads it from), and ``ros_distro: jazzy`` (rosbags
writes ``rosbags``) in ``metadata.yaml`` and in the file's ``rosbag2`` metadata record.
``metadata.yaml`` is version 9, Jazzy's, which Jazzy and later read; Humble's and Iron's
rosbag2 read ``offered_qos_profiles`` as a YAML string and fail on version 9's list.
"""

from __future__ import annotations

import contextlib
import json
import os
import signal
import struct
import sys
import time
import zlib
from collections import Counter
from io import BytesIO, StringIO
from pathlib import Path
from typing import BinaryIO, cast

from rosbags.interfaces import Connection, ConnectionExtRosbag2
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.rosbag2.storage_mcap import Channel, McapWriter, write_channel, write_string
from ruamel.yaml import YAML

HEADER = struct.Struct("<IQQ")
ROS_DISTRO = "jazzy"
"""The distribution the bag names as its recorder's (``ros2 bag`` writes ``$ROS_DISTRO``):
the first whose rosbag2 writes, and reads, ``metadata.yaml`` version 9, the version written."""
METADATA_VERSION = 9

# MCAP's layout (https://mcap.dev/spec): a record is an opcode byte, a uint64 length and the
# body, all little-endian.
_RECORD = struct.Struct("<BQ")
_DATA_END = 0x0F
_FOOTER = 0x02
_MAGIC = b"\x89MCAP0\r\n"
_CHUNK_CRC_AT = _RECORD.size + 3 * 8  # after message start and end time, uncompressed size
_FOOTER_SIZE = _RECORD.size + 8 + 8 + 4  # summary start, summary offset start, summary CRC


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


def _with_ros_distro(metadata_yaml: str) -> str:
    """rosbags' metadata YAML (``metadata.yaml``'s text, or its inner mapping as the MCAP
    ``rosbag2`` record holds it) with :data:`ROS_DISTRO` as its ``ros_distro``, written out
    the way rosbags writes it."""
    yaml = YAML(typ="safe")
    yaml.default_flow_style = False
    data = yaml.load(metadata_yaml)
    inner = data.get("rosbag2_bagfile_information", data)
    inner["ros_distro"] = ROS_DISTRO
    out = StringIO()
    yaml.dump(data, out)
    return out.getvalue()


def _seal(path: Path) -> None:
    """Write the CRC-32 of the data section into a closed MCAP file's DataEnd record, and that
    of the summary into its footer (MCAP: the data section is every byte from the file's
    start to DataEnd; the summary CRC covers the summary and summary offset sections and the
    footer up to the CRC itself)."""
    with open(path, "r+b") as f:
        footer_at = f.seek(0, os.SEEK_END) - len(_MAGIC) - _FOOTER_SIZE
        f.seek(footer_at)
        opcode, length, summary_start, _ = struct.unpack("<BQQQ", f.read(_FOOTER_SIZE - 4))
        data_end_at = summary_start - _RECORD.size - 4  # rosbags: DataEnd, then the summary
        if (opcode, length) == (_FOOTER, _FOOTER_SIZE - _RECORD.size) and data_end_at > 0:
            f.seek(data_end_at)
            if _RECORD.unpack(f.read(_RECORD.size)) == (_DATA_END, 4):
                data_crc = _crc_of(f, 0, data_end_at)
                summary_crc = _crc_of(f, summary_start, footer_at + _FOOTER_SIZE - 4)
                f.seek(data_end_at + _RECORD.size)
                f.write(data_crc.to_bytes(4, "little"))
                f.seek(footer_at + _FOOTER_SIZE - 4)
                f.write(summary_crc.to_bytes(4, "little"))
                return
    raise ValueError(f"{path}: no DataEnd record and footer where rosbags writes them")


def _crc_of(f: BinaryIO, start: int, stop: int, block: int = 1 << 22) -> int:
    """The CRC-32 of the bytes ``[start, stop)`` of ``f``, read in blocks (a bag is large)."""
    f.seek(start)
    crc = 0
    while (left := stop - f.tell()) > 0:
        crc = zlib.crc32(f.read(min(block, left)), crc)
    return crc


class McapStorage(McapWriter):
    """rosbags' MCAP storage, with what rosbag2's own MCAP writer writes and rosbags' leaves
    out: each chunk's CRC-32 (of its uncompressed records), each channel's
    ``topic_type_hash``, ``ros_distro`` in the ``rosbag2`` metadata record, and the CRC-32s of
    the data section and of the summary. Everything else is rosbags' own writing."""

    def add_connection(self, connection: Connection, offered_qos_profiles: str) -> None:
        """The channel as rosbags writes it, its metadata holding ``topic_type_hash`` beside
        ``offered_qos_profiles``, as ``rosbag2_storage_mcap`` writes them."""
        metadata = BytesIO()
        for text in ("offered_qos_profiles", offered_qos_profiles,
                     "topic_type_hash", connection.digest):
            write_string(metadata, text)
        ext = cast(ConnectionExtRosbag2, connection.ext)
        self.channels.append(Channel(connection.id, connection.msgtype, connection.topic,
                                     ext.serialization_format, metadata.getvalue()))
        self.channel_stats[connection.id] = 0
        write_channel(self.chunk.bio, self.channels[-1], self.schemas)

    def close_chunk(self) -> None:
        """rosbags' chunk, then its CRC written into it where rosbags writes 0."""
        with self.chunk.bio.getbuffer() as records:
            crc = zlib.crc32(records)
        start = self.bio.tell()
        super().close_chunk()
        end = self.bio.tell()
        self.bio.seek(start + _CHUNK_CRC_AT)
        self.bio.write(crc.to_bytes(4, "little"))
        self.bio.seek(end)

    def close(self, version: int, metadata: str) -> None:
        super().close(version, _with_ros_distro(metadata).strip())
        _seal(self.path)


class Rosbag2Writer(Writer):
    """rosbags' rosbag2 writer with :class:`McapStorage` for MCAP storage and
    :data:`ROS_DISTRO` in ``metadata.yaml``."""

    STORAGE_PLUGINS = {**Writer.STORAGE_PLUGINS, StoragePlugin.MCAP: McapStorage}

    def close(self) -> None:
        super().close()
        tmp = self.metapath.with_suffix(".yaml.tmp")  # replaced whole, as rosbags does
        tmp.write_text(_with_ros_distro(self.metapath.read_text("utf8")), "utf8")
        tmp.replace(self.metapath)


class BagFile:
    """A rosbag2 bag with MCAP storage of the given connections (:func:`connections`),
    written with rosbags: what both of the recorder's writers (its thread, or this module's
    process) write through."""

    def __init__(self, directory: Path, specs: list[dict[str, str]], compression: str) -> None:
        from rosbags.rosbag2.enums import CompressionFormat, CompressionMode

        self.directory = Path(directory)
        self.topics = [c["name"] for c in specs]
        self._writer = Rosbag2Writer(self.directory, version=METADATA_VERSION,
                                     storage_plugin=StoragePlugin.MCAP)
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
