"""The incremental maps (issue 30, :mod:`rovergate.streams`): every step's cloud rebuilt bit
for bit and in order from the step before's and the update, whatever changed; a reader that
lost its base refuses rather than guesses; forged updates are refused before they allocate;
the journal serves a restarted module a whole cloud made from its chain of updates."""

from __future__ import annotations

import contextlib

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from mission.runtime.journal import Journal
from rovergate.messages import MAX_POINTS, MessageError, decode, encode, patch_dtype
from rovergate.streams import (
    StreamDecoder,
    StreamEncoder,
    Wholes,
    apply,
    diff,
    keyframe,
)
from rovergate.types import PLANNER_DTYPE, SURFACE_DTYPE, CloudUpdate, PlannerMap

PROPERTY = settings(max_examples=120, deadline=None, derandomize=True,
                    suppress_health_check=[HealthCheck.too_slow])


def _surface(rng: np.random.Generator, n: int) -> np.ndarray:
    cloud = np.zeros(n, dtype=SURFACE_DTYPE)
    for axis in "xyz":  # on a 0.1 m lattice, as voxel centres are: repeats happen
        cloud[axis] = rng.integers(-50, 50, n) * np.float32(0.1)
    cloud["views"] = rng.integers(0, 6, n)
    return cloud


def _wire(topic: str, update: CloudUpdate) -> CloudUpdate:
    """The update as a reader gets it: through CDR."""
    return decode(topic, encode(topic, update))[1]


@PROPERTY
@given(seed=st.integers(0, 2**32 - 1), n=st.integers(0, 400), grow=st.integers(0, 100),
       seen=st.integers(0, 60), drop=st.integers(0, 50), shuffle=st.booleans())
def test_any_change_is_rebuilt_exactly(seed, n, grow, seen, drop, shuffle):
    """S_t's way (append, views up), the prediction's (points gone, points come, moved):
    the reader's cloud is the publisher's, byte for byte, order included."""
    rng = np.random.default_rng(seed)
    base = _surface(rng, n)
    new = np.concatenate([base, _surface(rng, grow)])
    if len(new) and seen:
        new["views"][rng.integers(0, len(new), seen)] += 1
    if len(new) and drop:
        new = np.delete(new, rng.integers(0, len(new), drop))
    if shuffle and len(new) > 2:
        cut = rng.integers(1, len(new))
        new = np.concatenate([new[cut:], new[:cut]])
    update = _wire("surface", diff(base, 4, new, 5))
    got = apply(base, update)
    assert got.dtype == new.dtype
    assert got.tobytes() == new.tobytes()


def test_a_growing_surface_sends_what_is_new_not_the_whole():
    rng = np.random.default_rng(1)
    base = _surface(rng, 50_000)
    new = np.concatenate([base, _surface(rng, 800)])
    new["views"][rng.choice(50_000, 4_000, replace=False)] += 1
    update = diff(base, 9, new, 10)
    assert not update.keyframe and update.base_step == 9
    assert len(update.points) == 800  # the new voxels, whole
    assert len(update.patch_at) == 4_000 and update.patches.dtype.names == ("views",)
    assert len(update.copy_to) == 1  # the old surface, copied in one run
    wire, whole = encode("surface", update), encode("surface", (10, new))
    assert len(wire) < 0.06 * len(whole)


def test_a_change_as_large_as_the_cloud_goes_whole():
    rng = np.random.default_rng(2)
    update = diff(_surface(rng, 300), 3, _surface(rng, 300), 4)
    assert update.keyframe and update.size == 300


def test_the_encoder_sends_keyframes_first_at_every_kth_step_and_on_a_redo():
    rng = np.random.default_rng(3)
    encoder = StreamEncoder("surface", keyframe_every=4, share=0)
    cloud = _surface(rng, 100)
    kinds = []
    for step in [1, 2, 3, 4, 5, 6, 6, 7]:  # the second 6: a restarted module redoing it
        cloud = np.concatenate([cloud, _surface(rng, 5)])
        kinds.append(encoder.encode((step, cloud)).keyframe)
    assert kinds == [True, False, False, True, False, False, True, False]


def test_keyframes_cost_no_more_than_the_updates_however_large_the_map():
    # A map of 20,000 points of which a step sees 2,000 again and adds 20 (a long traverse's,
    # in small): a keyframe comes at a multiple of 4 once the updates since the last add up
    # to the cloud, so the bytes of keyframes per step stay under those of the updates.
    rng = np.random.default_rng(9)
    encoder = StreamEncoder("surface", keyframe_every=4)
    cloud = _surface(rng, 20_000)
    keyframes, updates, at = 0, 0, []
    for step in range(1, 601):
        cloud = np.concatenate([cloud, _surface(rng, 20)])
        cloud["views"][rng.choice(len(cloud), 2_000, replace=False)] += 1
        u = encoder.encode((step, cloud))
        if u.keyframe:
            keyframes += cloud.nbytes
            at.append(step)
        else:
            updates += len(encode("surface", u))
    assert at[0] == 1 and all(s % 4 == 0 for s in at[1:]) and len(at) > 2
    assert keyframes - 20_020 * 14 <= 1.1 * updates  # the first keyframe aside
    gaps = np.diff(at[1:])
    assert gaps[-1] > gaps[0]  # rarer as the map grows


def test_a_planner_map_stream_gives_planner_maps_back():
    rng = np.random.default_rng(4)
    maps = []
    for step in range(6):
        cloud = np.zeros(200 + 10 * step, dtype=PLANNER_DTYPE)
        cloud["x"] = np.arange(len(cloud)) * 0.1
        cloud["views"] = rng.integers(0, 3, len(cloud))
        maps.append(PlannerMap(step, cloud))
    encoder, decoder = StreamEncoder("planner_map", 25), StreamDecoder("planner_map")
    for value in maps:
        back = decoder.apply(_wire("planner_map", encoder.encode(value)))
        assert isinstance(back, PlannerMap) and back.step == value.step
        assert back.points.tobytes() == value.points.tobytes()


def test_a_reader_without_the_base_refuses_and_a_keyframe_takes_it_up():
    rng = np.random.default_rng(5)
    clouds = [_surface(rng, 100)]
    for _ in range(4):
        clouds.append(np.concatenate([clouds[-1], _surface(rng, 10)]))
    encoder = StreamEncoder("surface", keyframe_every=3, share=0)
    updates = [encoder.encode((s, c)) for s, c in enumerate(clouds, start=1)]
    assert [u.keyframe for u in updates] == [True, False, True, False, False]
    late = StreamDecoder("surface")
    with pytest.raises(MessageError, match="applies to step 1; none is held"):
        late.apply(updates[1])
    assert late.offer(updates[1]) == []  # held, its base never comes
    whole = late.offer(updates[2])  # the keyframe
    assert [s for s, _ in whole] == [3]
    # Out of order: step 5 before step 4; both come out, in order, when 4 does.
    assert late.offer(updates[4]) == []
    out = late.offer(updates[3])
    assert [s for s, _ in out] == [4, 5]
    assert out[-1][1].tobytes() == clouds[-1].tobytes()


def _forged_update(data: st.DataObject, base: np.ndarray) -> CloudUpdate:
    u32 = st.integers(0, 2**32 - 1)
    small = st.integers(0, 2 * len(base) + 2)
    index = st.one_of(small, u32)
    runs = data.draw(st.integers(0, 4))
    points = data.draw(st.integers(0, 6))  # (at most the base's 20)
    size = data.draw(st.one_of(small, st.integers(0, MAX_POINTS + 5), u32))

    def table(n: int) -> np.ndarray:
        return np.array([data.draw(index) for _ in range(n)], dtype=np.uint32)
    patched = data.draw(st.integers(0, 3))
    patches = np.zeros(data.draw(st.sampled_from([patched, 0])), dtype=patch_dtype(base.dtype))
    return CloudUpdate(7, 6, size, base[:points], table(points), table(runs), table(runs),
                       table(data.draw(st.sampled_from([runs, 1]))), table(patched), patches)


@PROPERTY
@given(data=st.data())
def test_a_forged_update_is_refused_or_makes_exactly_its_cloud(data):
    """Whatever tables arrive, a reader gets a cloud of the size the update states, every
    point from its base or from the update, or a MessageError: never another exception and
    never an allocation past the limit."""
    base = _surface(np.random.default_rng(6), 20)
    update = _forged_update(data, base)
    with contextlib.suppress(MessageError):
        got = apply(base, update)
        assert len(got) == update.size <= MAX_POINTS
        known = {row.tobytes() for row in np.concatenate([base, update.points])}
        assert all(row.tobytes() in known for row in got)


def test_wholes_show_an_incremental_map_as_pointcloud2_from_its_first_keyframe():
    rng = np.random.default_rng(7)
    encoder = StreamEncoder("surface", keyframe_every=2, share=0)
    clouds, payloads = [_surface(rng, 30)], []
    for step in range(1, 6):
        clouds.append(np.concatenate([clouds[-1], _surface(rng, 3)]))
        payloads.append(encode("surface", encoder.encode((step, clouds[-1]))))
    wholes = Wholes()
    shown = [m for p in payloads[1:] for m in wholes.shown("surface", p)]  # joins late
    from rovergate.messages import TYPESTORE, cloud_from_ros
    steps = [cloud_from_ros(TYPESTORE.deserialize_cdr(m, "sensor_msgs/msg/PointCloud2"),
                            SURFACE_DTYPE) for m in shown]
    assert [s for s, _ in steps] == [2, 3, 4, 5]  # step 2 is the first keyframe it saw
    assert steps[-1][1].tobytes() == clouds[-1].tobytes()
    assert wholes.shown("depth", b"raw") == [b"raw"]  # other topics pass unchanged
    assert wholes.shown("surface", b"garbage") == [] and wholes.dropped == 1


def test_the_journal_serves_a_whole_cloud_and_keeps_the_chain_to_its_keyframe(tmp_path):
    rng = np.random.default_rng(8)
    encoder = StreamEncoder("surface", keyframe_every=5, share=0)
    journal = Journal(keep_last=3, path=tmp_path / "journal.sqlite")
    clouds = {}
    cloud = _surface(rng, 40)
    for step in range(1, 13):
        cloud = np.concatenate([cloud, _surface(rng, 4)])
        clouds[step] = cloud
        update = encoder.encode((step, cloud))
        journal.add("surface", step, encode("surface", update), keyframe=update.keyframe)
    # The last 3 steps (10..12) are needed, and the keyframe they are made from (10).
    assert journal.steps("surface") == [10, 11, 12]
    journal.close()
    reloaded = Journal(keep_last=3, path=tmp_path / "journal.sqlite")
    entries = list(reloaded.range("surface", 11, 12))
    first = decode("surface", entries[0].payload)[1]
    assert first.keyframe and first.step == 11  # made whole from 10 and 11's update
    decoder = StreamDecoder("surface")
    for entry in entries:
        decoder.apply(decode("surface", entry.payload)[1])
    assert decoder.step == 12 and decoder.cloud.tobytes() == clouds[12].tobytes()
    reloaded.close()


def test_a_keyframe_is_its_whole_value():
    cloud = _surface(np.random.default_rng(9), 10)
    update = keyframe("surface", (3, cloud))
    assert update.keyframe and apply(None, update) is cloud


def test_the_examples_reader_has_the_definition_and_rebuilds_what_rovergate_does():
    """examples/cloud_updates.py (no rovergate import) carries its own copy of the type and
    its own apply: both agree with rovergate's."""
    from pathlib import Path

    import cloud_updates
    from cloud_updates import CLOUD_UPDATE_MSG, MapStream
    from rosbags.typesys import Stores, get_typestore
    text = (Path(__file__).resolve().parents[1] / "rovergate/msg/CloudUpdate.msg").read_text()
    fields = [ln for ln in (x.split("#", 1)[0].strip() for x in text.splitlines()) if ln]
    assert CLOUD_UPDATE_MSG.splitlines() == fields, "copy rovergate/msg/CloudUpdate.msg's fields"
    store = get_typestore(Stores.ROS2_HUMBLE)
    cloud_updates.register(store)
    rng = np.random.default_rng(10)
    encoder, stream = StreamEncoder("planner_map", keyframe_every=3), MapStream()
    cloud = np.zeros(100, dtype=PLANNER_DTYPE)
    cloud["x"] = np.arange(100)
    for step in range(1, 8):
        cloud = np.concatenate([cloud, cloud[:5]])
        cloud["x"][-5:] = rng.normal(size=5) + 200 + step
        cloud["views"][rng.integers(0, len(cloud), 9)] += 1
        msg = store.deserialize_cdr(encode("planner_map", encoder.encode((step, cloud))),
                                    "rovergate_msgs/msg/CloudUpdate")
        assert stream.offer(msg) == [step]
        assert stream.rows.tobytes() == cloud.tobytes()
