"""Incremental map topics: each step's cloud sent as what changed since the step before.

The observed surface S_t, the learned prediction and the planner-facing map
(:data:`INCREMENTAL`) are whole clouds to the modules that read them, but most of a step's
cloud is the step before's again: S_t only grows (new voxels are appended, and the views of
the ones in sight go up), and the prediction moves by a few hundred voxels. On the wire, in
the journal and in the bag each of them travels as ``rovergate_msgs/msg/CloudUpdate``
(:class:`rovergate.types.CloudUpdate`):

- a **keyframe** (``base_step`` -1) carries the whole cloud. A publisher sends one as its
  first message (a restarted module's too), when the change would be larger than the cloud,
  and at a step that is a multiple of ``keyframe_every`` once the updates it sent since its
  last keyframe add up to the cloud's size (:meth:`StreamEncoder.encode`): in a 30 m box
  that is every 25 steps, and on a long traverse, where the map grows to millions of points
  and a step changes a few thousand, keyframes grow rarer as the map grows, so that they
  never cost more bytes than the updates do;
- an **update** of step t names the step of the publisher's previous message and carries the
  runs of points copied from that cloud, in order, plus the points that are new or changed,
  each with its position. Applied to the base, it gives the publisher's cloud bit for bit
  and in the same order, so a module reads exactly what the in-process loop hands over.

A reader keeps the last cloud of each topic (:class:`StreamDecoder`) and applies each
message in step order; one that joins late (a remote subscriber, the live view, a replay
started mid-bag) waits for the next keyframe, and a restarted module gets a keyframe of the
step it resumes at from the mission's journal (its first reply is whole, whatever was sent).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from rovergate.config import SessionConfig
from rovergate.graph import TOPICS
from rovergate.messages import MAX_POINTS, MessageError, cloud_cdr, decode, patch_dtype
from rovergate.types import CloudUpdate, PlannerMap, step_and_cloud

#: The topics that travel as :class:`rovergate.types.CloudUpdate`.
INCREMENTAL: frozenset[str] = frozenset(n for n, t in TOPICS.items() if t.incremental)
KEYFRAME_EVERY: int = SessionConfig.keyframe_every
"""Steps between keyframes by default (``--session.keyframe-every``)."""

MAX_PENDING = 256
"""Updates a reader holds for a base that has not come (a lost message): past it, the oldest
go; the next keyframe takes the stream up again."""

_LOOPED_RUNS = 256
"""Up to this many runs, an update's runs are copied slice by slice (memory copies); more,
by one gather."""

_KEY = 12  # every cloud's first 12 bytes are its float32 x, y, z
_MIX = (np.uint64(0x9E3779B97F4A7C15), np.uint64(0xC2B2AE3D27D4EB4F),
        np.uint64(0x165667B19E3779F9))


def value_of(topic: str, step: int, cloud: np.ndarray) -> Any:
    """What a reader of ``topic`` receives for ``cloud``: the array, or a PlannerMap."""
    return PlannerMap(step, cloud) if topic == "planner_map" else cloud


def keyframe(topic: str, value: Any) -> CloudUpdate:
    """The whole cloud of ``value`` as a keyframe."""
    step, cloud = step_and_cloud(value)
    return CloudUpdate(step, -1, len(cloud), cloud)


def _rows(cloud: np.ndarray) -> np.ndarray:
    """(N, itemsize) uint8: each point's bytes."""
    return np.ascontiguousarray(cloud).view(np.uint8).reshape(len(cloud), cloud.dtype.itemsize)


def _keys(rows: np.ndarray) -> np.ndarray:
    """(N,) uint64 hash of each point's x, y, z bytes (collisions are checked after)."""
    u = np.ascontiguousarray(rows[:, :_KEY]).view("<u4").astype(np.uint64)
    h: np.ndarray = (u[:, 0] * _MIX[0]) ^ (u[:, 1] * _MIX[1]) ^ (u[:, 2] * _MIX[2])
    return h


def _bits(cloud: np.ndarray, name: str) -> np.ndarray:
    """A field's values as unsigned integers of its size: compared bit for bit."""
    return cloud[name].view(f"<u{cloud.dtype.fields[name][0].itemsize}")  # type: ignore[index]


def _runs(copied: np.ndarray, froms: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(to, from, count) of the runs that copy ``froms`` to positions ``copied``."""
    if not len(copied):
        return copied, froms, copied
    cut = np.flatnonzero((np.diff(copied) != 1) | (np.diff(froms) != 1)) + 1
    starts = np.concatenate([[0], cut]).astype(np.int64)
    counts = np.diff(np.concatenate([starts, [len(copied)]]))
    return copied[starts], froms[starts], counts


def diff(base: np.ndarray, base_step: int, new: np.ndarray, step: int) -> CloudUpdate:
    """The update that makes ``new`` (step ``step``) from ``base`` (step ``base_step``), or a
    keyframe where that would be no smaller.

    Points are matched by their x, y, z: first the longest common prefix (S_t only appends),
    then the rest of ``new`` against the rest of ``base`` (a prediction that moved). A matched
    point is copied in a run; where its other fields changed (its views), a patch sets them;
    a point with no match is sent whole."""
    if base.dtype != new.dtype:
        raise ValueError(f"the base is {base.dtype}, the cloud {new.dtype}")
    others = [f for f in new.dtype.names or () if f not in ("x", "y", "z")]
    common = min(len(base), len(new))
    same_xyz = np.ones(common, dtype=bool)
    for axis in ("x", "y", "z"):
        same_xyz &= _bits(base, axis)[:common] == _bits(new, axis)[:common]
    k = common if same_xyz.all() else int(np.argmin(same_xyz))
    changed = np.zeros(k, dtype=bool)  # of the common prefix, copied in one run
    for f in others:
        changed |= _bits(base, f)[:k] != _bits(new, f)[:k]
    patch_at, put_at = [np.flatnonzero(changed)], [np.zeros(0, dtype=np.int64)]
    prefix = np.array([0] if k else [], dtype=np.int64)
    runs = [(prefix, prefix, prefix + k)]  # the prefix: one run, 0..k to 0..k
    if k < len(new):  # the rest, matched by hashing x, y, z
        src = np.full(len(new) - k, -1, dtype=np.int64)
        b, n = _rows(base[k:]), _rows(new[k:])
        if len(b):
            rest_keys = _keys(b)
            order = np.argsort(rest_keys, kind="stable")
            sorted_keys = rest_keys[order]
            want = _keys(n)
            at = np.minimum(np.searchsorted(sorted_keys, want), len(sorted_keys) - 1)
            found = np.where(sorted_keys[at] == want, order[at], -1)
            hit = np.flatnonzero(found >= 0)
            real = (b[found[hit], :_KEY] == n[hit, :_KEY]).all(axis=1)  # not a collision
            src[hit[real]] = found[hit[real]]
        copied = np.flatnonzero(src >= 0)
        patch_at.append(copied[(b[src[copied], _KEY:] != n[copied, _KEY:]).any(axis=1)] + k)
        put_at.append(np.flatnonzero(src < 0) + k)
        r_to, r_from, r_count = _runs(copied, src[copied])
        runs.append((r_to + k, r_from + k, r_count))
    at_patch, at_put = np.concatenate(patch_at), np.concatenate(put_at)
    to, froms, counts = (np.concatenate([r[i] for r in runs]) for i in range(3))
    item, fields = new.dtype.itemsize, patch_dtype(new.dtype)
    sent = len(at_put) * (item + 4) + len(at_patch) * (fields.itemsize + 4) + 12 * len(to)
    if sent >= len(new) * item:
        return CloudUpdate(step, -1, len(new), new)
    u32 = np.uint32
    patches = np.empty(len(at_patch), dtype=fields)
    for name in others:
        patches[name] = new[name][at_patch]
    return CloudUpdate(step, base_step, len(new), new[at_put], at_put.astype(u32),
                       to.astype(u32), froms.astype(u32), counts.astype(u32),
                       at_patch.astype(u32), patches)


def apply(base: np.ndarray | None, update: CloudUpdate) -> np.ndarray:
    """The cloud ``update`` makes from ``base`` (None: there is none; only a keyframe
    applies). Raises :class:`rovergate.messages.MessageError` when the update does not fit
    its base or does not fill its cloud exactly once."""
    if update.keyframe:
        if len(update.points) != update.size:
            raise MessageError(f"keyframe of step {update.step} says {update.size} points and "
                               f"carries {len(update.points)}")
        return update.points
    if base is None:
        raise MessageError(f"update of step {update.step} applies to step "
                           f"{update.base_step}, and no cloud is held")
    size = int(update.size)
    if size > MAX_POINTS:
        raise MessageError(f"update of {size} points is over the limit of {MAX_POINTS}")
    runs = (update.copy_to, update.copy_from, update.copy_count)
    patches = update.patches if update.patches is not None else np.empty(
        0, dtype=patch_dtype(base.dtype))
    if (len({len(r) for r in runs}) != 1 or len(update.put_at) != len(update.points)
            or len(update.patch_at) != len(patches)):
        raise MessageError(f"update of step {update.step}: its tables differ in length")
    counts = update.copy_count.astype(np.int64)
    total = int(counts.sum())
    if total + len(update.put_at) != size:
        raise MessageError(f"update of step {update.step} fills {total + len(update.put_at)} "
                           f"of its {size} points")
    to, start = update.copy_to.astype(np.int64), update.copy_from.astype(np.int64)
    put_at = update.put_at.astype(np.int64)
    patch_at = update.patch_at.astype(np.int64)
    if ((len(counts) and ((to + counts).max() > size or (start + counts).max() > len(base)))
            or (len(put_at) and put_at.max() >= size)
            or (len(patch_at) and patch_at.max() >= size)):
        raise MessageError(f"update of step {update.step} reaches past its cloud or its base")
    out = np.empty(size, dtype=base.dtype)
    filled = np.zeros(size, dtype=bool)
    if len(counts) <= _LOOPED_RUNS:  # few runs (S_t: one): copied as slices
        for t, f, c in zip(to.tolist(), start.tolist(), counts.tolist(), strict=True):
            out[t:t + c] = base[f:f + c]
            filled[t:t + c] = True
    else:
        within = np.arange(total, dtype=np.int64) - np.repeat(np.cumsum(counts) - counts, counts)
        dst = np.repeat(to, counts) + within
        out[dst] = base[np.repeat(start, counts) + within]
        filled[dst] = True
    filled[put_at] = True
    if not filled.all():
        raise MessageError(f"update of step {update.step} fills some points twice and others "
                           "never")
    out[put_at] = update.points
    for name in patches.dtype.names or ():
        out[name][patch_at] = patches[name]
    return out


class StreamEncoder:
    """A publisher's side of one incremental topic: each step's value -> a CloudUpdate."""

    def __init__(self, topic: str, keyframe_every: int = KEYFRAME_EVERY,
                 share: float = 1.0) -> None:
        """``share``: a keyframe is due at a multiple of ``keyframe_every`` once the updates
        since the last one add up to this share of the cloud's size (0: at every multiple)."""
        self.topic = topic
        self.keyframe_every = max(1, int(keyframe_every))
        self.share = share
        self._last: tuple[int, np.ndarray] | None = None
        self._since = 0
        """Bytes of the updates sent since the last keyframe."""

    def encode(self, value: Any) -> CloudUpdate:
        """The message of ``value``'s step: a keyframe as its first, after a step that did
        not come before it, and at a multiple of ``keyframe_every`` once the updates since
        the last keyframe add up to the cloud's own size (so that keyframes cost at most what
        the updates do, however large the map: in a 30 m box every 25 steps, on a long
        traverse's map of millions of points hundreds of steps apart); else an update."""
        step, cloud = step_and_cloud(value)
        last, self._last = self._last, (step, cloud)
        if (last is None or step <= last[0]
                or (step % self.keyframe_every == 0
                    and self._since >= self.share * cloud.nbytes)):
            self._since = 0
            return CloudUpdate(step, -1, len(cloud), cloud)
        update = diff(last[1], last[0], cloud, step)
        self._since = 0 if update.keyframe else self._since + update_nbytes(update)
        return update


def update_nbytes(update: CloudUpdate) -> int:
    """The bytes of an update's arrays (what it costs beside its fixed fields)."""
    arrays = (update.points, update.put_at, update.copy_to, update.copy_from,
              update.copy_count, update.patch_at, update.patches)
    return sum(int(a.nbytes) for a in arrays if a is not None)


class StreamDecoder:
    """A reader's side of one incremental topic: the last cloud, and each message applied.

    :meth:`apply` takes messages strictly in order (a module's lockstep); :meth:`offer` takes
    them as they arrive and gives back the values that became whole, holding an update
    whose base has not come yet and dropping one made from a step it no longer holds."""

    def __init__(self, topic: str) -> None:
        self.topic = topic
        self.step: int | None = None
        self.cloud: np.ndarray | None = None
        self._pending: dict[int, CloudUpdate] = {}

    def apply(self, update: CloudUpdate) -> Any:
        """The value of ``update``'s step (a keyframe, or an update of the step held).
        Raises MessageError otherwise."""
        if not update.keyframe and update.base_step != self.step:
            held = "none" if self.step is None else f"step {self.step}"
            raise MessageError(f"{self.topic} update of step {update.step} applies to step "
                               f"{update.base_step}; {held} is held")
        self.cloud = apply(self.cloud, update)
        self.step = update.step
        return value_of(self.topic, update.step, self.cloud)

    def offer(self, update: CloudUpdate) -> list[tuple[int, Any]]:
        """``(step, value)`` of every step ``update`` completes, in order (none while it
        waits for its base, or for a keyframe)."""
        if not update.keyframe and update.base_step != self.step:
            if self.step is None or update.base_step > self.step:
                self._pending[update.base_step] = update
                while len(self._pending) > MAX_PENDING:  # a lost message: await a keyframe
                    del self._pending[min(self._pending)]
            return []
        out = [(update.step, self.apply(update))]
        while self.step in self._pending:
            nxt = self._pending.pop(self.step)
            out.append((nxt.step, self.apply(nxt)))
        for s in [s for s in self._pending if self.step is not None and s < self.step]:
            del self._pending[s]
        return out


POINTCLOUD2 = "sensor_msgs/msg/PointCloud2"


def shown_type(topic: str) -> str:
    """The ROS 2 type a viewer of whole maps shows ``topic`` as: PointCloud2 for an
    incremental map (:class:`Wholes`), the topic's own type for the others."""
    return POINTCLOUD2 if topic in INCREMENTAL else TOPICS[topic].msgtype


class Wholes:
    """A stream of payloads with the incremental maps made whole again, as
    ``sensor_msgs/msg/PointCloud2`` CDR: what the live view, the ROS 2 bridge and a replay
    to them send on, so that Foxglove and ``ros2 topic echo`` show the whole map. Until a
    topic's first keyframe comes it shows nothing of it."""

    def __init__(self) -> None:
        self._decoders: dict[str, StreamDecoder] = {}
        self.dropped = 0

    def shown(self, topic: str, payload: bytes) -> list[bytes]:
        """The messages to show for one payload of ``topic`` (none, one, or several when
        it completes updates held for it)."""
        if topic not in INCREMENTAL:
            return [payload]
        try:
            update = decode(topic, payload)[1]
            decoder = self._decoders.setdefault(topic, StreamDecoder(topic))
            done = decoder.offer(update)
        except MessageError:
            self.dropped += 1
            return []
        return [cloud_cdr(step, value.points if isinstance(value, PlannerMap) else value)
                for step, value in done]
