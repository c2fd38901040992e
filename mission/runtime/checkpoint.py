"""The mission manager's checkpoint: what ``rovergate run --out OUT --resume`` needs to carry
on a mission whose manager was killed.

Three files under ``OUT`` hold a process-set mission's state as it runs:

- ``journal.sqlite``: every sample the modules rebuild their state from
  (:class:`mission.runtime.journal.Journal`, written through as samples arrive);
- ``downlink.sqlite``: the onboard telemetry queue (:mod:`mission.link.downlink`);
- ``checkpoint.sqlite`` (:data:`CHECKPOINT`): the loop's own state at the last step boundary
  it passed (:class:`LoopState`): the next step, the record so far, the configuration as
  ground commands left it, the link's clock and what was in flight on it, and the
  transport's counts. It is written append-only: each step adds one row with what the step
  appended to the record's histories and the transport's timings (:func:`appendables`), and
  replaces one row with the rest, which does not grow with the mission; both in one
  transaction. Its cost per step is therefore constant, where pickling the whole record
  after every step cost O(T) bytes a step, O(T^2) over a mission.

On ``--resume`` the manager loads them, starts every module again at the step before the
checkpoint's (each redoes it from the journal, deterministically, as a module restarted after
its own crash does) and runs the loop on from the checkpoint's step. Each row of the
checkpoint is read with an unpickler that builds only this project's data classes, numpy
arrays and Python's plain types: loading a file that names anything else refuses it, and
runs nothing. (The checkpoint is as trusted as the rest of ``OUT``: it holds the mission's
configuration, and a configuration names the programs a mission runs.)
"""

from __future__ import annotations

import dataclasses
import io
import pickle
import sqlite3
from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path
from typing import Any

from mission.scoring.record import MissionRecord
from rovergate.config import MissionConfig
from rovergate.errors import ConfigError
from rovergate.types import Pose

CHECKPOINT = "checkpoint.sqlite"
LEGACY = "checkpoint.pickle"
"""The whole-record checkpoint of earlier versions (removed with a new mission's)."""
VERSION = 2
#: Fields of :class:`MissionRecord` that are dicts of histories (each list grows by appends).
_DICTS_OF_LISTS = ("stage_s",)

_SCHEMA = """
CREATE TABLE IF NOT EXISTS state (id INTEGER PRIMARY KEY CHECK (id = 1), step INTEGER NOT NULL,
                                  blob BLOB NOT NULL);
CREATE TABLE IF NOT EXISTS appended (row INTEGER PRIMARY KEY AUTOINCREMENT,
                                     step INTEGER NOT NULL, blob BLOB NOT NULL);
"""


@dataclass
class LoopState:
    """The mission loop between two steps."""

    step: int
    """The next step to run (every step before it is in ``record``)."""
    record: MissionRecord
    collisions: int
    previous_base: Pose | None
    condition: str
    cfg: MissionConfig
    """The configuration as it stands (ground commands may have changed it)."""
    operations: dict[str, Any] | None = None
    """:meth:`mission.link.operations.Operations.snapshot` (None without the ground link)."""
    transport: dict[str, Any] = field(default_factory=dict)
    """:meth:`mission.runtime.process_set.ProcessSetTransport.snapshot`."""
    saved_at: str = ""
    version: int = VERSION


def appendables(state: LoopState) -> dict[str, list[Any]]:
    """The histories of ``state`` that only grow by appends, by name: every list of the
    record (``record.coverage``, ...), each list of its dicts of lists
    (``record.stage_s.plan``, ...), and the transport's timings."""
    out: dict[str, list[Any]] = {}
    for f in dataclasses.fields(MissionRecord):
        value = getattr(state.record, f.name)
        if isinstance(value, list):
            out[f"record.{f.name}"] = value
        elif f.name in _DICTS_OF_LISTS:
            for key, values in value.items():
                out[f"record.{f.name}.{key}"] = values
    timings = state.transport.get("timings")
    if isinstance(timings, list):
        out["transport.timings"] = timings
    return out


def _skeleton(state: LoopState) -> LoopState:
    """``state`` without its histories (they go in the appended rows)."""
    empty: dict[str, Any] = {}
    for f in dataclasses.fields(MissionRecord):
        value = getattr(state.record, f.name)
        if isinstance(value, list):
            empty[f.name] = []
        elif f.name in _DICTS_OF_LISTS:
            empty[f.name] = {}
    transport = dict(state.transport)
    if isinstance(transport.get("timings"), list):
        transport["timings"] = []
    return dataclasses.replace(state, record=dataclasses.replace(state.record, **empty),
                               transport=transport)


def _extend(state: LoopState, name: str, values: list[Any]) -> None:
    """Append ``values`` to the history ``name`` of ``state`` (:func:`appendables`)."""
    where, _, rest = name.partition(".")
    if where == "transport":
        state.transport.setdefault(rest, []).extend(values)
        return
    field_name, _, key = rest.partition(".")
    if key:
        getattr(state.record, field_name).setdefault(key, []).extend(values)
    else:
        getattr(state.record, field_name).extend(values)


def _connect(path: Path) -> sqlite3.Connection:
    db = sqlite3.connect(path, isolation_level=None)
    db.execute("PRAGMA journal_mode=WAL")  # a SIGKILL leaves the last committed step
    db.execute("PRAGMA synchronous=NORMAL")
    db.executescript(_SCHEMA)
    return db


class CheckpointWriter:
    """Writes a mission's checkpoint into ``OUT/checkpoint.sqlite`` after every step, append
    only. ``resumed``: the state a resumed mission starts from (its histories are on disk
    already)."""

    def __init__(self, out: Path, resumed: LoopState | None = None) -> None:
        self.path = Path(out) / CHECKPOINT
        self.db = _connect(self.path)
        self._written: dict[str, int] = {}
        if resumed is not None:
            self._written = {k: len(v) for k, v in appendables(resumed).items()}
        self.bytes_written = 0
        """Bytes of the rows written by the last :meth:`save`."""

    def save(self, state: LoopState) -> None:
        """The state at a step boundary: what its histories appended since the last save,
        and the rest, in one transaction (a killed manager leaves the last whole step)."""
        state.saved_at = datetime.now().astimezone().isoformat(timespec="seconds")
        histories = appendables(state)
        rewrite = any(len(v) < self._written.get(k, 0) for k, v in histories.items())
        if rewrite:  # a history that shrank (never, today): write it all again
            self._written = {}
        new = {k: v[self._written.get(k, 0):] for k, v in histories.items()}
        new = {k: v for k, v in new.items() if v}
        rest = pickle.dumps(_skeleton(state), protocol=pickle.HIGHEST_PROTOCOL)
        delta = pickle.dumps(new, protocol=pickle.HIGHEST_PROTOCOL)
        with self.db:
            self.db.execute("BEGIN IMMEDIATE")
            if rewrite:
                self.db.execute("DELETE FROM appended")
            self.db.execute("INSERT INTO appended (step, blob) VALUES (?, ?)",
                            (state.step, delta))
            self.db.execute("INSERT OR REPLACE INTO state (id, step, blob) VALUES (1, ?, ?)",
                            (state.step, rest))
        self._written = {k: len(v) for k, v in histories.items()}
        self.bytes_written = len(rest) + len(delta)

    def close(self) -> None:
        self.db.close()


def remove(out: Path) -> None:
    """Remove the checkpoint (this version's and an earlier one's), and any temp file a
    killed manager of an earlier version left half written."""
    out = Path(out)
    for path in [out / CHECKPOINT, out / f"{CHECKPOINT}-wal", out / f"{CHECKPOINT}-shm",
                 out / LEGACY, *out.glob(f".{LEGACY}.tmp-*")]:
        path.unlink(missing_ok=True)


_BUILTINS = frozenset({"list", "dict", "set", "frozenset", "tuple", "str", "int", "float",
                       "bool", "bytes", "bytearray", "complex", "slice", "range"})
_NUMPY = frozenset({("numpy", "ndarray"), ("numpy", "dtype"),
                    ("numpy.core.multiarray", "_reconstruct"),
                    ("numpy._core.multiarray", "_reconstruct"),
                    ("numpy.core.multiarray", "scalar"), ("numpy._core.multiarray", "scalar"),
                    ("numpy", "float64"), ("numpy", "float32"), ("numpy", "int64"),
                    ("numpy", "bool_"), ("numpy.core.numeric", "_frombuffer"),
                    ("numpy._core.numeric", "_frombuffer")})
_OURS = ("mission.", "rovergate.", "planner.", "mapper.", "gate.", "rover_sim.")


class _Unpickler(pickle.Unpickler):
    """Builds plain data only: the project's classes, numpy arrays, Python's containers."""

    def find_class(self, module: str, name: str) -> Any:
        if "." in name:  # pickle resolves dotted names: mission.x + subprocess.Popen
            raise pickle.UnpicklingError(f"it names {module}.{name}, which a checkpoint "
                                         "never holds")
        if module == "builtins" and name in _BUILTINS:
            return super().find_class(module, name)
        if (module, name) in _NUMPY or (module == "copyreg" and name == "_reconstructor"):
            return super().find_class(module, name)
        if module == "pathlib" and name in ("PosixPath", "PurePosixPath", "Path"):
            return super().find_class(module, name)
        if module.startswith(_OURS):
            obj = super().find_class(module, name)
            # A data class of ours (built without running its __init__); never a function,
            # nor a class that does something when made.
            if isinstance(obj, type) and dataclasses.is_dataclass(obj):
                return obj
        raise pickle.UnpicklingError(f"it names {module}.{name}, which a checkpoint never "
                                     "holds")


def _unpickle(data: bytes) -> Any:
    return _Unpickler(io.BytesIO(data)).load()


def load(out: Path) -> LoopState:
    """The checkpoint in ``out``; a missing, damaged or foreign file is a ConfigError."""
    path = Path(out) / CHECKPOINT
    if not path.exists():
        if (Path(out) / LEGACY).exists():
            raise ConfigError(f"--resume: {Path(out) / LEGACY} is the checkpoint of an earlier "
                              "rovergate version, which this one does not read; run the "
                              "mission again without --resume, in a new --out")
        raise ConfigError(f"--resume: {path} does not exist: the mission in {out} ended, or "
                          "never passed a step boundary in the process set; run it without "
                          "--resume") from None
    try:
        db = sqlite3.connect(f"file:{path}?mode=ro", uri=True)
        try:
            row = db.execute("SELECT blob FROM state WHERE id = 1").fetchone()
            if row is None:
                raise ValueError("it holds no state")
            state = _unpickle(row[0])
            if not isinstance(state, LoopState) or state.version != VERSION:
                raise _Foreign
            for (blob,) in db.execute("SELECT blob FROM appended ORDER BY row"):
                appended = _unpickle(blob)
                if not isinstance(appended, dict):
                    raise ValueError("a row of histories is not a mapping")
                for name, values in appended.items():
                    if not isinstance(name, str) or not isinstance(values, list):
                        raise ValueError(f"history {name!r} is not a list")
                    _extend(state, name, values)
        finally:
            db.close()
    except _Foreign:
        raise ConfigError(f"--resume: {path} is not a checkpoint of this rovergate version; "
                          "run the mission again without --resume, in a new --out") from None
    except Exception as exc:  # any damage: one line, never a traceback
        raise ConfigError(f"--resume: {path} is not a rovergate checkpoint ({exc}); run the "
                          "mission again without --resume, in a new --out") from None
    return state


class _Foreign(Exception):
    """A checkpoint of another version."""
