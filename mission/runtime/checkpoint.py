"""The mission manager's checkpoint: what ``rovergate run --out OUT --resume`` needs to carry
on a mission whose manager was killed.

Three files under ``OUT`` hold a process-set mission's state as it runs:

- ``journal.sqlite``: every sample the modules rebuild their state from
  (:class:`mission.runtime.journal.Journal`, written through as samples arrive);
- ``downlink.sqlite``: the onboard telemetry queue (:mod:`mission.link.downlink`);
- ``checkpoint.pickle`` (:data:`CHECKPOINT`): the loop's own state at the last step boundary
  it passed (:class:`LoopState`): the next step, the record so far, the configuration as
  ground commands left it, the link's clock and what was in flight on it, and the
  transport's counts. It is replaced whole (temp file and rename) after every step.

On ``--resume`` the manager loads them, starts every module again at the step before the
checkpoint's (each redoes it from the journal, deterministically, as a module restarted after
its own crash does) and runs the loop on from the checkpoint's step. The checkpoint is read
with an unpickler that builds only this project's data classes, numpy arrays and Python's
plain types: loading a file that names anything else refuses it, and runs nothing. (The
checkpoint is as trusted as the rest of ``OUT``: it holds the mission's configuration, and a
configuration names the programs a mission runs.)
"""

from __future__ import annotations

import dataclasses
import io
import os
import pickle
from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path
from typing import Any

from mission.scoring.record import MissionRecord
from rovergate.config import MissionConfig
from rovergate.errors import ConfigError
from rovergate.types import Pose

CHECKPOINT = "checkpoint.pickle"
VERSION = 1


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


def save(state: LoopState, out: Path) -> None:
    """Write ``OUT/checkpoint.pickle`` whole or not at all."""
    state.saved_at = datetime.now().astimezone().isoformat(timespec="seconds")
    path = Path(out) / CHECKPOINT
    tmp = path.with_name(f".{CHECKPOINT}.tmp-{os.getpid()}")
    tmp.write_bytes(pickle.dumps(state, protocol=pickle.HIGHEST_PROTOCOL))
    os.replace(tmp, path)


def remove(out: Path) -> None:
    """Remove the checkpoint, and any temp file a killed manager left half written."""
    for path in [Path(out) / CHECKPOINT, *Path(out).glob(f".{CHECKPOINT}.tmp-*")]:
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


def load(out: Path) -> LoopState:
    """The checkpoint in ``out``; a missing, damaged or foreign file is a ConfigError."""
    path = Path(out) / CHECKPOINT
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        raise ConfigError(f"--resume: {path} does not exist: the mission in {out} ended, or "
                          "never passed a step boundary in the process set; run it without "
                          "--resume") from None
    except OSError as exc:
        raise ConfigError(f"--resume: cannot read {path} ({exc})") from None
    try:
        state = _Unpickler(io.BytesIO(data)).load()
    except Exception as exc:  # any damage: one line, never a traceback
        raise ConfigError(f"--resume: {path} is not a rovergate checkpoint ({exc}); run the "
                          "mission again without --resume, in a new --out") from None
    if not isinstance(state, LoopState) or state.version != VERSION:
        raise ConfigError(f"--resume: {path} is not a checkpoint of this rovergate version; "
                          "run the mission again without --resume, in a new --out")
    return state
