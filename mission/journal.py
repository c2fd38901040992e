"""The mission's journal: the samples of past steps that a restarted module replays.

Every module is a deterministic function of its input streams, so a module that died is
rebuilt by feeding it its past inputs again (:meth:`rovergate.node.ModuleNode.resume`). The
mission keeps those inputs here, as the raw bytes that travelled on the wire:
every step of the topics a module rebuilds its state from (``KEEP_ALL``: a depth image of
the default 160 x 120 camera is 77 kB, so 100 steps hold about 8 MB), and the last few steps
of the bulky per-step products (``keep_last``), which a restarted module needs only for the
step it resumes at.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass

#: Topics journalled for every step: what the modules rebuild their state from.
KEEP_ALL = frozenset({"status", "path", "depth", "camera_info", "pose", "base_pose"})
#: Topics journalled for the last ``keep_last`` steps only: a step's live inputs.
KEEP_LAST = frozenset({"surface", "predicted", "planner_map"})


@dataclass(frozen=True)
class Entry:
    """One journalled sample: its step and its CDR bytes (the topic fixes the encoding)."""

    step: int
    payload: bytes


class Journal:
    """Per-topic, per-step store of samples (plain data; the hub serves it over Zenoh)."""

    def __init__(self, keep_last: int = 3) -> None:
        self.keep_last = keep_last
        self._entries: dict[str, dict[int, Entry]] = {t: {} for t in KEEP_ALL | KEEP_LAST}

    @property
    def topics(self) -> frozenset[str]:
        return KEEP_ALL | KEEP_LAST

    def add(self, topic: str, step: int, payload: bytes) -> None:
        """Record a sample (a repeated step replaces the earlier one: replays are
        deterministic, so both hold the same bytes)."""
        entries = self._entries[topic]
        entries[step] = Entry(step, payload)
        if topic in KEEP_LAST:
            for old in [s for s in entries if s <= step - self.keep_last]:
                del entries[old]

    def range(self, topic: str, first: int, last: int) -> Iterator[Entry]:
        """The samples of steps ``first..last`` (inclusive) that the journal holds, by step."""
        entries = self._entries.get(topic, {})
        for step in sorted(s for s in entries if first <= s <= last):
            yield entries[step]

    def nbytes(self) -> int:
        return sum(len(e.payload) for entries in self._entries.values()
                   for e in entries.values())
