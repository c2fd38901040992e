"""The flight recorder and replay (issue 17, part 1): every mission records every topic its
modules publish into a rosbag2 MCAP bag that readers other than ours decode, and
``rovergate replay`` publishes it again, byte for byte, over Zenoh."""

from __future__ import annotations

import os
import re
import struct
import subprocess
import zlib
from pathlib import Path

import numpy as np
import pytest
import zenoh
from mcap.reader import make_reader
from mcap.records import Chunk, DataEnd, Footer
from mcap.stream_reader import StreamReader, breakup_chunk
from mcap_ros2.decoder import DecoderFactory
from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from ruamel.yaml import YAML

from rovergate.config import SessionConfig
from rovergate.graph import TOPICS
from rovergate.keys import Keys
from rovergate.session import free_loopback_port, zenoh_config
from rovergate.taps import tapped_topics
from tests.conftest import ROVERGATE, Waiter, read_metrics, recorded_mission, run_cli

PLANNER = "/rover/map/occupancy/planner"


def _mcap(bag: Path) -> Path:
    (path,) = bag.glob("*.mcap")
    return path


def _decoded(bag: Path, topics: list[str]) -> dict[str, list]:
    """Every message of ``topics``, decoded by the mcap package's ROS 2 decoder (written from
    the message definitions in the file, not with our codec)."""
    out: dict[str, list] = {t: [] for t in topics}
    with open(_mcap(bag), "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        for schema, channel, _, msg in reader.iter_decoded_messages(topics=topics):
            assert schema.encoding == "ros2msg" and channel.message_encoding == "cdr"
            out[channel.topic].append(msg)
    return out


def _jazzy_rihs01() -> dict[str, str]:
    """Every recorded type's RIHS01 hash as a Jazzy node computes it, from rosbags' Jazzy
    store and the .msg files (not from rovergate's own type store)."""
    store = get_typestore(Stores.ROS2_JAZZY)
    msg_dir = Path(__file__).resolve().parents[1] / "rovergate" / "msg"
    types = {}
    for path in sorted(msg_dir.glob("*.msg")):
        types.update(get_types_from_msg(path.read_text(), f"rovergate_msgs/msg/{path.stem}"))
    store.register(types)
    return {t: store.hash_rihs01(t) for t in {TOPICS[t].msgtype for t in tapped_topics()}}


def _check_as_rosbag2_writes_it(bag: Path) -> None:
    """The bag's MCAP file as rosbag2's own writer makes it: every CRC there and right (the
    mcap reader checks the chunks' and the data section's; the summary's, which it does not,
    is computed here from the spec), each channel's ``topic_type_hash`` the RIHS01 hash of
    its type, and Jazzy's ``ros_distro`` and metadata version."""
    path = _mcap(bag)
    with open(path, "rb") as f:  # CRCValidationError on a wrong data section CRC
        records = list(StreamReader(f, validate_crcs=True, emit_chunks=True).records)
    chunks = [r for r in records if isinstance(r, Chunk)]
    (data_end,) = [r for r in records if isinstance(r, DataEnd)]
    (footer,) = [r for r in records if isinstance(r, Footer)]
    assert chunks and all(c.uncompressed_crc != 0 for c in chunks)  # 0: "not computed"
    assert data_end.data_section_crc != 0 and footer.summary_crc != 0
    for chunk in chunks:  # and on a wrong chunk CRC (of its records, decompressed)
        breakup_chunk(chunk, validate_crc=True)
    data = path.read_bytes()
    footer_at = len(data) - 8 - (1 + 8 + 8 + 8 + 4)  # the footer, then the magic
    assert data[footer_at] == 0x02
    summary_start, summary_offset_start, summary_crc = struct.unpack_from(
        "<QQI", data, footer_at + 9)
    assert summary_start > 0 and summary_offset_start > summary_start
    # MCAP: the summary CRC covers the summary through the footer's summary_offset_start.
    assert zlib.crc32(data[summary_start:footer_at + 9 + 16]) == summary_crc
    with open(path, "rb") as f:
        reader = make_reader(f, validate_crcs=True)
        summary = reader.get_summary()
        assert sum(1 for _ in reader.iter_messages()) == summary.statistics.message_count
        (record,) = [m for m in reader.iter_metadata() if m.name == "rosbag2"]
    hashes = _jazzy_rihs01()
    for channel in summary.channels.values():
        schema = summary.schemas[channel.schema_id]
        assert channel.metadata["topic_type_hash"] == hashes[schema.name], channel.topic
        assert channel.metadata["offered_qos_profiles"] == "[]"
    info = YAML(typ="safe").load((bag / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    assert (info["version"], info["ros_distro"]) == (9, "jazzy")
    assert {t["topic_metadata"]["name"]: t["topic_metadata"]["type_description_hash"]
            for t in info["topics_with_message_count"]} == {
        c.topic: c.metadata["topic_type_hash"] for c in summary.channels.values()}
    embedded = YAML(typ="safe").load(record.metadata["serialized_metadata"])
    assert (embedded["version"], embedded["ros_distro"]) == (9, "jazzy")


def test_an_in_process_missions_bag_has_rosbag2s_crcs_type_hashes_and_distro(recorded: Path):
    _check_as_rosbag2_writes_it(recorded / "bag")  # zstd chunks, the writer's own process


def test_a_recorder_threads_bag_has_rosbag2s_crcs_type_hashes_and_distro(tmp_path: Path):
    """Uncompressed, written on the recorder's thread, several chunks (rosbags closes one
    past 1 MiB)."""
    from ecosystem.recorder import FlightRecorder
    from rovergate.messages import encode
    from rovergate.types import MissionStatus
    recorder = FlightRecorder(tmp_path / "bag", writer="thread")
    for step in range(4):
        recorder.put("status", encode("status", MissionStatus(step, 4, "running", "obs", 0.0,
                                                              0)), step + 1)
        recorder.put("surface", os.urandom(700_000), step + 1)  # bytes as they came
    recorder.close()
    _check_as_rosbag2_writes_it(tmp_path / "bag")
    with open(_mcap(tmp_path / "bag"), "rb") as f:
        assert sum(isinstance(r, Chunk) for r in StreamReader(f, emit_chunks=True).records) > 1


def _whole(updates) -> dict[str, np.ndarray]:
    """The last cloud of a stream of CloudUpdates (as mcap-ros2-support decodes them), made
    whole by the example's reader (which imports nothing of rovergate), as fields."""
    from cloud_updates import MapStream
    stream = MapStream()
    done = [s for m in updates for s in stream.offer(m)]
    assert done == [m.header.stamp.sec for m in updates]
    return {f.name: stream.field(f.name) for f in stream.fields}


@pytest.mark.e2e
def test_a_process_set_mission_records_every_topic_into_an_mcap_bag(tmp_path: Path):
    out = tmp_path / "run"
    r = run_cli("run", "--steps", "10", "--out", str(out), "--seed", "3")
    assert r.returncode == 0, r.stderr[-3000:]
    bag = out / "bag"
    assert (bag / "metadata.yaml").is_file()
    keys = Keys("rover")
    names = {t: "/" + keys.key(t) for t in tapped_topics()}
    got = _decoded(bag, list(names.values()))
    # A planner-facing map for every planning step, in order, decoded independently.
    maps = got[PLANNER]
    assert [m.header.stamp.sec for m in maps] == list(range(10))
    assert maps[0].base_step == -1  # the first is whole; the others, what changed
    assert all(m.base_step == m.header.stamp.sec - 1 for m in maps[1:])
    last = _whole(maps)
    assert set(last) == {"x", "y", "z", "source", "views", "channels"}
    assert len(last["x"]) > 0 and set(np.unique(last["channels"])) <= {1, 2, 3}
    # The last surface is the S_T the report scores.
    metrics = read_metrics(out)
    surfaces = got[names["surface"]]
    assert [m.header.stamp.sec for m in surfaces] == list(range(11))
    assert len(_whole(surfaces)["x"]) == metrics["observed_points"]
    # S_t only grows: after the first (whole), each message carries its new voxels alone
    # (and patches of the views of those seen again), not the whole surface again.
    assert [m.base_step for m in surfaces] == [-1, *range(10)]
    new = sum(m.points.width for m in surfaces[1:])
    assert new == metrics["observed_points"] - surfaces[0].size
    assert new + surfaces[0].size < 0.25 * sum(m.size for m in surfaces)
    # Each path starts where the base was when it was planned (two topics, two publishers;
    # the planner's z is its own terrain estimate).
    bases = got[names["base_pose"]]
    paths = got[names["path"]]
    assert len(bases) == 11 and len(paths) == 10
    for base, path in zip(bases, paths, strict=False):
        p, q = base.pose.position, path.poses[0].pose.position
        assert (p.x, p.y) == pytest.approx((q.x, q.y), abs=1e-6)
    # Every topic is there, as many times as the report says it was written.
    counts = {t: len(got[n]) for t, n in names.items()}
    assert counts == metrics["recording"]["messages"]
    assert counts["status"] == 12  # ticks 0..10 and the final `done`
    assert metrics["recording"]["writer"] == "thread"  # the mission manager's own thread
    # The rover's hazard cameras and its traversability map, decoded independently.
    for end in ("front", "rear"):
        images = got[names[f"hazcam_{end}"]]
        assert [m.header.stamp.sec for m in images] == list(range(11))
        img = images[0]
        assert img.encoding == "32FC1" and img.header.frame_id == f"hazcam_{end}_optical"
        assert (img.width, img.height) == (128, 96) and len(img.data) == 4 * 128 * 96
        depth = np.frombuffer(bytes(img.data), "<f4")
        assert np.isfinite(depth).mean() > 0.5  # the ground ahead (behind) of the rover
        info = got[names[f"hazcam_{end}_info"]][0]
        assert info.header.frame_id == f"hazcam_{end}_optical" and info.k[0] > 0
    grids = got[names["traversability"]]
    assert [m.header.stamp.sec for m in grids] == list(range(10))
    cells = np.array(list(grids[-1].data), dtype=np.int8)  # int8[]: a list of ints
    assert len(cells) == grids[-1].info.width * grids[-1].info.height
    assert grids[-1].info.resolution == pytest.approx(0.1)
    assert set(np.unique(cells)) <= {-1, 0, 100} and (cells == 0).sum() > 1000
    reports = got[names["traverse"]]
    assert [m.step for m in reports] == list(range(10))
    assert {m.reason for m in reports} <= {"best-feasible", "rotate", "escape", "backout",
                                            "stay"}


@pytest.fixture(scope="module")
def recorded(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("recorded") / "run"
    recorded_mission(out, 3, "--platform", "flyer", "--record-compression", "zstd")
    return out


def test_an_in_process_mission_records_what_the_process_set_would_send(recorded: Path):
    metrics = read_metrics(recorded)
    rec = metrics["recording"]
    assert rec["compression"] == "zstd" and rec["file_bytes"] < rec["payload_bytes"]
    assert rec["writer"] == "process"  # off the loop's Python lock
    got = _decoded(recorded / "bag", [PLANNER, "/rover/sensor/pose", "/rover/sensor/depth"])
    assert [m.header.stamp.sec for m in got[PLANNER]] == [0, 1, 2]
    pose = got["/rover/sensor/pose"][-1]
    q = pose.pose.orientation
    assert pose.header.frame_id == "map"
    assert q.x**2 + q.y**2 + q.z**2 + q.w**2 == pytest.approx(1.0, abs=1e-6)
    depth = got["/rover/sensor/depth"][0]
    assert depth.encoding == "32FC1" and len(depth.data) == 4 * depth.width * depth.height


def test_no_record_writes_no_bag(tmp_path: Path):
    out = tmp_path / "run"
    r = run_cli("run", "--in-process", "--steps", "1", "--out", str(out), "--no-record")
    assert r.returncode == 0, r.stderr[-3000:]
    assert not (out / "bag").exists() and read_metrics(out)["recording"] == {}


def test_replay_publishes_the_bag_again_byte_for_byte(recorded: Path):
    from rosbags.rosbag2 import Reader
    with Reader(recorded / "bag") as reader:
        expected = [(c.topic.lstrip("/"), c.msgtype, bytes(data))
                    for c, _, data in reader.messages()]
        span_s = (reader.end_time - reader.start_time) / 1e9
    endpoint = f"tcp/127.0.0.1:{free_loopback_port()}"
    received: list[tuple[str, str, bytes]] = []
    waiter = Waiter()

    def on_sample(sample: zenoh.Sample) -> None:
        received.append((str(sample.key_expr), str(sample.encoding),
                         sample.payload.to_bytes()))
        waiter.notify()

    with zenoh.open(zenoh_config(SessionConfig(listen=(endpoint,)))) as session:
        sub = session.declare_subscriber("replayed/**", on_sample)
        speed = 0.5
        proc = subprocess.run(
            [*ROVERGATE, "replay", str(recorded / "bag"), "--speed", str(speed),
             "--namespace", "replayed", "--listen", "--connect", endpoint,
             "--wait-subscriber-s", "60"], capture_output=True, text=True, timeout=120)
        assert proc.returncode == 0, proc.stderr[-3000:]
        waiter.wait_for(lambda: len(received) >= len(expected), 30, "replayed messages",
                        lambda: f" ({len(received)} of {len(expected)})")
        sub.undeclare()
    assert len(received) == len(expected)
    for (key, encoding, data), (topic, msgtype, want) in zip(received, expected, strict=True):
        assert key == "replayed/" + topic.split("/", 1)[1]
        assert encoding == f"application/cdr;{msgtype}"
        assert data == want
    # Paced: it took at least the recording's span over the speed.
    m = re.search(r"replayed (\d+) messages .* of ([\d.]+) s of recording in ([\d.]+) s",
                  proc.stderr)
    assert m and int(m.group(1)) == len(expected), proc.stderr[-2000:]
    wall = float(m.group(3))
    assert wall >= span_s / speed * 0.95
    assert {TOPICS[t].msgtype for t in tapped_topics()} == {m for _, m, _ in expected}


def _replay(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([*ROVERGATE, "replay", *args], capture_output=True, text=True,
                          timeout=60)


def test_replay_refuses_what_is_not_a_closed_bag(tmp_path: Path):
    r = _replay(str(tmp_path / "nothing"))
    assert r.returncode == 2 and "is not a bag directory" in r.stderr
    (tmp_path / "open").mkdir()
    (tmp_path / "open" / "open.mcap").write_bytes(b"\x89MCAP0\r\n")
    r = _replay(str(tmp_path / "open"))
    assert r.returncode == 2 and "no metadata.yaml" in r.stderr


def test_a_failing_tap_is_stopped_and_the_others_go_on(caplog):
    from rovergate.taps import Taps

    class Full:
        closed = False

        def put(self, topic, payload, time_ns):
            raise OSError("No space left on device")

        def close(self):
            Full.closed = True

    class Keeps:
        def __init__(self):
            self.got = []

        def put(self, topic, payload, time_ns):
            self.got.append(payload)

        def close(self):
            pass

    keeps = Keeps()
    taps = Taps([Full(), keeps])
    taps.put("status", b"a")
    taps.put("status", b"b")
    assert keeps.got == [b"a", b"b"] and Full.closed and taps.taps == [keeps]
    assert "Full failed and is stopped: No space left on device" in caplog.text


def test_a_recorder_whose_writer_dies_says_so_and_does_not_hold_the_mission(tmp_path: Path):
    from ecosystem.recorder import FlightRecorder
    from rovergate.messages import encode
    from rovergate.types import MissionStatus
    recorder = FlightRecorder(tmp_path / "bag", writer="process")
    payload = encode("status", MissionStatus(0, 5, "running", "obs", 0.0, 0))
    recorder.put("status", payload, 1)
    recorder._proc.kill()  # the writer process dies (out of memory, killed, ...)
    recorder._proc.wait(30)
    big = b"\0" * (1 << 20)  # more than a pipe holds: a writer that blocked would hang here
    for t in range(4):
        try:
            recorder.put("surface", big, t)
        except RuntimeError as exc:  # once the recorder knows, it says so to the taps
            assert "stopped" in str(exc)
            break
    with pytest.raises(RuntimeError, match="stopped early"):
        recorder.close()
    assert recorder.stats.error


def test_a_killed_in_process_mission_leaves_a_closed_bag(tmp_path: Path):
    """The writer process closes the bag when its input ends, however the mission's process
    ends."""
    import signal
    import sys
    code = ("import sys, time; from pathlib import Path; "
            "from ecosystem.recorder import FlightRecorder; "
            "from rovergate.messages import encode; from rovergate.types import MissionStatus; "
            "r = FlightRecorder(Path(sys.argv[1]), writer='process'); "
            "[r.put('status', encode('status', MissionStatus(s, 9, 'running', 'obs', 0.0, 0)),"
            " s) for s in range(5)]; r.flush(); print(r._proc.pid, flush=True); "
            "time.sleep(600)")
    proc = subprocess.Popen([sys.executable, "-c", code, str(tmp_path / "bag")],
                            stdout=subprocess.PIPE, text=True)
    writer = int(proc.stdout.readline())
    proc.send_signal(signal.SIGKILL)
    proc.wait(30)
    from rosbags.rosbag2 import Reader

    from tests.conftest import wait_gone
    # The writer sees the end of its input, closes the bag and exits.
    assert wait_gone(writer, 60), "the bag writer did not exit within 60 s of the mission"
    with Reader(tmp_path / "bag") as reader:
        assert [c.msgcount for c in reader.connections if c.topic.endswith("status")] == [5]


def test_a_recorder_thread_that_cannot_write_says_so_in_its_stats(tmp_path: Path):
    from ecosystem.recorder import FlightRecorder
    from rovergate.messages import encode
    from rovergate.types import MissionStatus
    recorder = FlightRecorder(tmp_path / "bag", writer="thread")
    payload = encode("status", MissionStatus(0, 5, "running", "obs", 0.0, 0))
    recorder.put("status", payload, 1)
    assert recorder.flush()
    recorder._bag._writer.storage.bio.close()  # the file goes away under it (a full disk)
    with pytest.raises(RuntimeError, match="stopped early"):
        recorder.close()
    assert recorder.stats.error == "ValueError: I/O operation on closed file"


def test_replay_that_would_reach_no_one_is_refused(recorded: Path):
    r = _replay(str(recorded / "bag"))
    assert r.returncode == 2 and "would reach no one" in r.stderr


def test_a_replay_waits_for_its_first_subscriber_by_default_and_says_when_none_came():
    import threading

    from ecosystem.replay import ReplayConfig, _await_subscriber
    from rovergate.config import ConfigError
    assert ReplayConfig(bag=Path("bag")).wait_subscriber_s >= 30  # a late subscriber misses nothing
    watched = threading.Event()
    with pytest.raises(ConfigError, match=r"no subscriber within 0 s \(--wait-subscriber-s\)"):
        _await_subscriber([], [watched.is_set], 0.2, threading.Event())
    watched.set()
    _await_subscriber([], [watched.is_set], 0.2, threading.Event())  # returns: one is watching
