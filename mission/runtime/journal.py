"""The mission's journal: the samples of past steps that a restarted module replays.

Every module is a deterministic function of its input streams, so a module that died is
rebuilt by feeding it its past inputs again (:meth:`rovergate.node.ModuleNode.resume`). The
mission keeps those inputs here, as the raw bytes that travelled on the wire:
every step of the topics a module rebuilds its state from (``KEEP_ALL``: a depth image of
the default 160 x 120 camera is 77 kB, so 100 steps hold about 8 MB), and the last few steps
of the bulky per-step products (``keep_last``), which a restarted module needs only for the
step it resumes at. Which topics go where is derived from the graph
(:func:`rovergate.graph.journal_topics`).

:class:`Journal` is plain data, written through to ``OUT/journal.sqlite`` in the process set
(so that ``rovergate run --resume`` rebuilds every module after the mission manager itself
died); :class:`JournalServer` answers a restarted module's queries for it over Zenoh.
"""

from __future__ import annotations

import logging
import sqlite3
import threading
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import zenoh

from rovergate.errors import ConfigError
from rovergate.graph import journal_topics
from rovergate.keys import Keys
from rovergate.messages import MessageError, decode, encode
from rovergate.node import cdr_encoding
from rovergate.streams import INCREMENTAL, StreamDecoder, keyframe

log = logging.getLogger("rovergate.mission")

JOURNAL = "journal.sqlite"
"""The journal's file in the mission's directory (process set)."""

#: Topics journalled for every step (what the modules rebuild their state from, and the
#: ticks), and for the last ``keep_last`` steps only (a step's other inputs).
KEEP_ALL, KEEP_LAST = journal_topics()


@dataclass(frozen=True)
class Entry:
    """One journalled sample: its step and its CDR bytes (the topic fixes the encoding)."""

    step: int
    payload: bytes
    keyframe: bool = True
    """An incremental map's message that is whole (:mod:`rovergate.streams`); every other
    topic's message is."""


_SCHEMA = """
CREATE TABLE IF NOT EXISTS entries (
    topic TEXT NOT NULL, step INTEGER NOT NULL, payload BLOB NOT NULL,
    keyframe INTEGER NOT NULL DEFAULT 1,
    PRIMARY KEY (topic, step)
);
"""


class Journal:
    """Per-topic, per-step store of samples (plain data; :class:`JournalServer` serves it).

    With a ``path``, every change is written through to that SQLite file (WAL, no fsync per
    sample: what was written survives the process being killed, though not necessarily a
    power cut), and what the file holds is loaded first. Not thread-safe: its callers hold
    the mission's lock."""

    def __init__(self, keep_last: int = 3, path: Path | None = None) -> None:
        self.keep_last = keep_last
        self._entries: dict[str, dict[int, Entry]] = {t: {} for t in KEEP_ALL | KEEP_LAST}
        self.path = path
        self._db: sqlite3.Connection | None = None
        if path is not None:
            try:
                self._db = sqlite3.connect(path, isolation_level=None, check_same_thread=False)
                self._db.execute("PRAGMA journal_mode=WAL")
                self._db.execute("PRAGMA synchronous=NORMAL")
                self._db.executescript(_SCHEMA)
                held = sorted(t for t in self._entries if not self._on_disk(t))
                marks = ",".join("?" * len(held))
                rows = self._db.execute(
                    f"SELECT topic, step, CASE WHEN topic IN ({marks}) THEN payload ELSE x'' "
                    "END, keyframe FROM entries", held).fetchall()
            except sqlite3.DatabaseError as exc:
                raise ConfigError(f"the mission's journal {path} is not a usable SQLite file "
                                  f"({exc}); give --out a directory this user can write (a "
                                  "mission cannot --resume without its journal: start it "
                                  "again in a new --out)") from None
            for topic, step, payload, whole in rows:
                if topic in self._entries:
                    self._entries[topic][int(step)] = Entry(
                        int(step), b"" if self._on_disk(topic) else bytes(payload), bool(whole))

    def _on_disk(self, topic: str) -> bool:
        """Whether ``topic``'s payloads are read from the file rather than held: those of
        every step (KEEP_ALL, a depth image and more a step) when there is a file, so that
        the mission manager's memory does not grow with the mission's length."""
        return self._db is not None and topic in KEEP_ALL and topic not in INCREMENTAL

    def close(self) -> None:
        if self._db is not None:
            self._db.close()
            self._db = None

    @property
    def topics(self) -> frozenset[str]:
        return KEEP_ALL | KEEP_LAST

    def add(self, topic: str, step: int, payload: bytes, keyframe: bool = True) -> None:
        """Record a sample (``keyframe``: an incremental map's message is whole). A repeated
        step keeps the first: replays are deterministic, so a module that redoes a step sends
        the same bytes, and anything else sent later for a step already recorded is not what
        the mission ran on."""
        entries = self._entries[topic]
        if step in entries:
            return
        entries[step] = Entry(step, b"" if self._on_disk(topic) else payload, keyframe)
        horizon = step - self.keep_last  # steps up to here are no longer needed
        if topic in INCREMENTAL:
            # ...but an update needs the chain back to its keyframe: keep from the latest
            # keyframe that the steps still needed are made from.
            whole = [s for s, e in entries.items() if e.keyframe and s <= horizon + 1]
            horizon = max(whole) - 1 if whole else -1
        old = [s for s in entries if s <= horizon] if topic in KEEP_LAST else []
        for s in old:
            del entries[s]
        if self._db is not None:
            with self._db:
                self._db.execute("BEGIN")
                self._db.execute("INSERT OR IGNORE INTO entries VALUES (?, ?, ?, ?)",
                                 (topic, step, payload, int(keyframe)))
                if old:
                    self._db.execute("DELETE FROM entries WHERE topic = ? AND step <= ?",
                                     (topic, horizon))

    def steps(self, topic: str) -> list[int]:
        """The steps of ``topic`` the journal holds, in order."""
        return sorted(self._entries.get(topic, {}))

    def range(self, topic: str, first: int, last: int) -> Iterator[Entry]:
        """The samples of steps ``first..last`` (inclusive) that the journal holds, by step.
        Of an incremental map, the first is a keyframe (made from the chain of updates since
        the keyframe before it), so that a module that had none can take the rest up."""
        entries = self._entries.get(topic, {})
        steps = sorted(s for s in entries if first <= s <= last)
        if topic in INCREMENTAL and steps and not entries[steps[0]].keyframe:
            whole = self._whole(topic, steps[0])
            if whole is not None:  # (else nothing to make it from: not servable)
                yield whole
            steps = steps[1:]
        if self._on_disk(topic) and steps:
            assert self._db is not None
            rows = self._db.execute(
                "SELECT step, payload FROM entries WHERE topic = ? AND step BETWEEN ? AND ? "
                "ORDER BY step", (topic, steps[0], steps[-1]))
            for step, payload in rows:
                yield Entry(int(step), bytes(payload), entries[int(step)].keyframe)
            return
        for step in steps:
            yield entries[step]

    def _whole(self, topic: str, step: int) -> Entry | None:
        """A keyframe of ``step`` of an incremental map, or None when the journal does not
        hold the chain back to a keyframe."""
        entries = self._entries[topic]
        starts = [s for s, e in entries.items() if e.keyframe and s <= step]
        if not starts:
            return None
        decoder = StreamDecoder(topic)
        try:
            for s in range(max(starts), step + 1):
                if s in entries:
                    decoder.apply(decode(topic, entries[s].payload)[1])
        except MessageError as exc:
            log.warning("journal: cannot make %s of step %d whole: %s", topic, step, exc)
            return None
        if decoder.step != step or decoder.cloud is None:
            return None
        return Entry(step, encode(topic, keyframe(topic, (step, decoder.cloud))))

    def nbytes(self) -> int:
        """Bytes of the payloads journalled (held, and in the file only)."""
        held = sum(len(e.payload) for entries in self._entries.values()
                   for e in entries.values())
        if self._db is None:
            return held
        disk = [t for t in self._entries if self._on_disk(t)]
        if not disk:
            return held
        marks = ",".join("?" * len(disk))
        row = self._db.execute("SELECT COALESCE(SUM(LENGTH(payload)), 0) FROM entries WHERE "
                               f"topic IN ({marks})", disk).fetchone()
        return held + int(row[0])


class JournalServer:
    """Answers ``<ns>/mission/journal/<key>?from=A;to=B`` with the journalled samples of steps
    A..B, one reply per step (a restarted module's replay)."""

    def __init__(self, session: zenoh.Session, keys: Keys, journal: Journal,
                 lock: threading.Condition | threading.Lock) -> None:
        self.journal = journal
        self._lock = lock
        self._queryables = [session.declare_queryable(keys.journal(t), self._on_query(keys, t))
                            for t in journal.topics]

    def _on_query(self, keys: Keys, topic: str):
        key = keys.journal(topic)
        encoding = cdr_encoding(topic)

        def on_query(query: zenoh.Query) -> None:
            try:
                first = int(query.parameters.get("from", "0"))
                last = int(query.parameters.get("to", str(first)))
            except ValueError:
                log.warning("journal query %s has non-integer from/to; ignored", query.selector)
                return
            with self._lock:
                entries = list(self.journal.range(topic, first, last))
            for entry in entries:
                query.reply(key, entry.payload, encoding=encoding)
        return on_query

    def close(self) -> None:
        for q in self._queryables:
            q.undeclare()
