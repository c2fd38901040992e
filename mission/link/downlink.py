"""The onboard store-and-forward queue of telemetry, on disk (SQLite).

Telemetry waits here between contact windows. Inside a window the bridge takes items in
priority order (:data:`PRIORITY`: events first, then mission status, then pose, then map
snapshots; oldest first within a class) as far as the window's rate allows, and the ground
acknowledges each one by sequence number. The queue survives a restart of the mission
manager: it is a SQLite file written in a transaction per change.

Sequence numbers: an item gets the next number when it is first radiated and keeps it until
the ground acknowledges it; an item radiated again (its acknowledgement did not come by the
time the contact plan says it should have) goes with the same number. Numbers are therefore
contiguous in the order the ground first receives items, and the ground drops any number it
has already recorded: it sees no gap and no duplicate.

Storage policy (bounded by ``max_bytes``):
- a newer map snapshot supersedes an older one that was not yet radiated;
- over the bound, the oldest not-yet-radiated status and pose samples are dropped, oldest
  first, and the count of dropped samples goes down as an event;
- events (module restarts, command acknowledgements, mission state) are never dropped; an item
  once radiated is kept until it is acknowledged.
"""

from __future__ import annotations

import sqlite3
from dataclasses import dataclass
from pathlib import Path

from rovergate.errors import ConfigError

#: Downlink priority of each kind of item (lower goes first).
PRIORITY: dict[str, int] = {"event": 0, "command_ack": 0, "status": 1, "pose": 2, "map": 3}
#: Kinds that may be dropped when the queue is over its bound.
DROPPABLE = ("status", "pose")
#: Kinds of which only the newest unsent item is kept.
SUPERSEDED = ("map",)

_SCHEMA = """
CREATE TABLE IF NOT EXISTS items (
    id INTEGER PRIMARY KEY AUTOINCREMENT,
    kind TEXT NOT NULL,
    priority INTEGER NOT NULL,
    msgtype TEXT NOT NULL,
    step INTEGER NOT NULL,
    payload BLOB NOT NULL,
    size INTEGER NOT NULL,
    seq INTEGER,
    due_s REAL
);
CREATE INDEX IF NOT EXISTS items_order ON items (priority, id);
CREATE TABLE IF NOT EXISTS meta (key TEXT PRIMARY KEY, value INTEGER NOT NULL);
INSERT OR IGNORE INTO meta VALUES ('next_seq', 1);
INSERT OR IGNORE INTO meta VALUES ('dropped', 0);
"""


@dataclass(frozen=True)
class Item:
    """One telemetry item: a ROS 2 message (CDR bytes of ``msgtype``) and where it stands."""

    id: int
    kind: str
    msgtype: str
    step: int
    payload: bytes
    seq: int | None = None


class DownlinkQueue:
    """A persistent, bounded, prioritised queue of telemetry items (one SQLite file)."""

    def __init__(self, path: Path, max_bytes: int = 64 * 2**20) -> None:
        self.path = Path(path)
        self.max_bytes = max_bytes
        self.path.parent.mkdir(parents=True, exist_ok=True)
        try:
            self._db = sqlite3.connect(self.path, isolation_level=None,
                                       check_same_thread=False)
            self._db.execute("PRAGMA journal_mode=WAL")
            self._db.execute("PRAGMA synchronous=NORMAL")
            self._db.executescript(_SCHEMA)
        except sqlite3.DatabaseError as exc:
            raise ConfigError(f"the downlink queue {self.path} is not a usable SQLite "
                              f"file ({exc}); move it away to start with an empty queue") from None

    def close(self) -> None:
        self._db.close()

    # --- onboard: store -------------------------------------------------------------------

    def put(self, kind: str, msgtype: str, step: int, payload: bytes) -> int:
        """Store an item; returns its id. Applies the storage policy (module docstring)."""
        if kind not in PRIORITY:
            raise ValueError(f"unknown telemetry kind {kind!r}; one of {sorted(PRIORITY)}")
        with self._db:
            self._db.execute("BEGIN IMMEDIATE")
            if kind in SUPERSEDED:
                self._db.execute("DELETE FROM items WHERE kind = ? AND seq IS NULL", (kind,))
            cur = self._db.execute(
                "INSERT INTO items (kind, priority, msgtype, step, payload, size) "
                "VALUES (?, ?, ?, ?, ?, ?)",
                (kind, PRIORITY[kind], msgtype, step, payload, len(payload)))
            item_id = int(cur.lastrowid)
            self._enforce_bound()
        return item_id

    def _enforce_bound(self) -> None:
        over = self.nbytes() - self.max_bytes
        if over <= 0:
            return
        marks = ",".join("?" * len(DROPPABLE))
        rows = self._db.execute(
            f"SELECT id, size FROM items WHERE seq IS NULL AND kind IN ({marks}) "
            "ORDER BY id", DROPPABLE).fetchall()
        drop = []
        for item_id, size in rows:
            if over <= 0:
                break
            drop.append(item_id)
            over -= size
        if drop:
            self._db.executemany("DELETE FROM items WHERE id = ?", [(i,) for i in drop])
            self._db.execute("UPDATE meta SET value = value + ? WHERE key = 'dropped'",
                             (len(drop),))

    # --- onboard: radiate -----------------------------------------------------------------

    def take(self, budget_bytes: int, now_s: float, due_s: float) -> list[Item]:
        """Items to radiate now, in priority order, within ``budget_bytes``: those never sent,
        and those whose acknowledgement was due by ``now_s`` and has not come. Stops at the
        first item that does not fit (a later, smaller one does not jump the queue). Numbers
        the items never sent; ``due_s`` is when their acknowledgement is due."""
        out: list[Item] = []
        with self._db:
            self._db.execute("BEGIN IMMEDIATE")
            rows = self._db.execute(
                "SELECT id, kind, msgtype, step, payload, size, seq FROM items "
                "WHERE seq IS NULL OR due_s <= ? ORDER BY priority, id", (now_s,))
            next_seq = self._meta("next_seq")
            left = budget_bytes
            updates = []
            for item_id, kind, msgtype, step, payload, size, seq in rows:
                if size > left:
                    break
                left -= size
                if seq is None:
                    seq, next_seq = next_seq, next_seq + 1
                updates.append((seq, due_s, item_id))
                out.append(Item(item_id, kind, msgtype, step, bytes(payload), seq))
            self._db.executemany("UPDATE items SET seq = ?, due_s = ? WHERE id = ?", updates)
            self._db.execute("UPDATE meta SET value = ? WHERE key = 'next_seq'", (next_seq,))
        return out

    def ack(self, seqs: list[int]) -> int:
        """The ground has these sequence numbers: forget them. Returns how many were held."""
        if not seqs:
            return 0
        with self._db:
            cur = self._db.executemany("DELETE FROM items WHERE seq = ?", [(s,) for s in seqs])
        return cur.rowcount

    # --- state ----------------------------------------------------------------------------

    def _meta(self, key: str) -> int:
        return int(self._db.execute("SELECT value FROM meta WHERE key = ?", (key,)).fetchone()[0])

    @property
    def dropped(self) -> int:
        """Status and pose samples dropped over the bound, ever."""
        return self._meta("dropped")

    def __len__(self) -> int:
        return int(self._db.execute("SELECT COUNT(*) FROM items").fetchone()[0])

    def nbytes(self) -> int:
        return int(self._db.execute("SELECT COALESCE(SUM(size), 0) FROM items").fetchone()[0])

    def unacked(self) -> int:
        """Items radiated and not yet acknowledged."""
        return int(self._db.execute(
            "SELECT COUNT(*) FROM items WHERE seq IS NOT NULL").fetchone()[0])
