"""Read rovergate's incremental maps with numpy and rosbags alone (no rovergate import).

``<ns>/map/surface``, ``<ns>/map/occupancy/predicted`` and ``<ns>/map/occupancy/planner``
travel as ``rovergate_msgs/msg/CloudUpdate`` (docs/architecture.md, "Incremental maps"): a
keyframe (``base_step`` -1) carries the whole cloud as its ``points``; an update carries runs
copied from the cloud of step ``base_step``, the points that are new, with their positions,
and patches of the other fields (the views) of copied points that changed. :class:`MapStream`
keeps the last cloud and applies each message (a rosbags message, or any object with the same
fields, as ``mcap-ros2-support`` decodes); a reader that joins late sees the map from the next
keyframe (every 25 steps by default).
"""

from __future__ import annotations

import numpy as np
from rosbags.typesys import get_types_from_msg

CLOUD_UPDATE = "rovergate_msgs/msg/CloudUpdate"
CLOUD_UPDATE_MSG = """std_msgs/Header header
int32 base_step
uint32 size
uint32[] copy_to
uint32[] copy_from
uint32[] copy_count
uint32[] put_at
sensor_msgs/PointCloud2 points
uint32[] patch_at
sensor_msgs/PointCloud2 patches
"""


def register(store) -> None:
    """Declare the CloudUpdate type to a rosbags typestore."""
    store.register(get_types_from_msg(CLOUD_UPDATE_MSG, CLOUD_UPDATE))


def _sizes(cloud) -> list[int]:
    """The byte size of each field of a PointCloud2 (int8/uint8 1, int16/uint16 2, else 4
    or 8)."""
    return [{1: 1, 2: 1, 3: 2, 4: 2, 5: 4, 6: 4, 7: 4, 8: 8}[f.datatype] for f in cloud.fields]


class MapStream:
    """One incremental map made whole: :meth:`offer` each message as it arrives."""

    def __init__(self) -> None:
        self.step: int | None = None
        self.rows: np.ndarray | None = None  # (N, point_step) uint8: the points' bytes
        self.fields: list = []  # the PointCloud2's fields (name, offset, datatype)
        self._waiting: dict[int, object] = {}  # updates whose base has not come, by base

    def offer(self, msg) -> list[int]:
        """Apply a CloudUpdate (and any update it lets through); the steps made whole."""
        if msg.base_step >= 0 and msg.base_step != self.step:
            if self.step is None or msg.base_step > self.step:
                self._waiting[msg.base_step] = msg
            return []
        done = []
        while msg is not None:
            self._apply(msg)
            done.append(self.step)
            msg = self._waiting.pop(self.step, None)
        return done

    def _apply(self, msg) -> None:
        pts = msg.points
        rows = np.frombuffer(bytes(pts.data), dtype=np.uint8).reshape(-1, pts.point_step)
        if msg.base_step < 0:
            whole = rows.copy()
        else:
            whole = np.empty((msg.size, pts.point_step), dtype=np.uint8)
            for to, start, n in zip(msg.copy_to, msg.copy_from, msg.copy_count, strict=True):
                whole[to:to + n] = self.rows[start:start + n]
            whole[np.asarray(msg.put_at, dtype=np.int64)] = rows
            patch = msg.patches  # the fields but x, y, z of copied points that changed
            patched = np.frombuffer(bytes(patch.data), dtype=np.uint8).reshape(
                -1, patch.point_step)
            at = np.asarray(msg.patch_at, dtype=np.int64)
            where = {f.name: f.offset for f in pts.fields}
            for f, size in zip(patch.fields, _sizes(patch), strict=True):
                whole[at, where[f.name]:where[f.name] + size] = patched[:, f.offset:f.offset + size]
        self.rows, self.fields, self.step = whole, list(pts.fields), int(msg.header.stamp.sec)

    def field(self, name: str) -> np.ndarray:
        """One field of the whole cloud as an array (float32, uint8 or uint16 fields)."""
        kinds = {2: "u1", 4: "<u2", 7: "<f4"}
        f = next(f for f in self.fields if f.name == name)
        dt = np.dtype(kinds[f.datatype])
        return self.rows[:, f.offset:f.offset + dt.itemsize].copy().view(dt)[:, 0]

    def xyz(self) -> np.ndarray:
        """(N, 3) float32."""
        return np.stack([self.field(k) for k in "xyz"], axis=1)
