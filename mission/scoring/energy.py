"""What a run cost: its CPU seconds, its process's peak memory, and an energy estimate.

The energy model (docs/study.md, "Latency, memory and energy"), per run:

- **Drive**: metres driven times the energy a metre costs. For the rover, a Mars Exploration
  Rover figure: about 100 W to drive (NASA, MER "Rover Energy",
  https://mars.nasa.gov/mer/mission/rover/energy/) at the fastest speed it was commanded to
  drive, 3.7 cm/s (Guinness World Records, "Land speed record on Mars", 2022, after NASA/JPL):
  100 / 0.037 = 2,700 J a metre. Hazard-avoidance stops and slower driving make the real figure
  larger (MER averaged about 1 cm/s with autonomous navigation), so this is a lower bound of the
  drive's energy. The flyer has no such figure in our sources: a rotorcraft's energy follows
  its time aloft, not its path, so its drive energy is left out (None), not guessed.
- **Compute**: the run's CPU seconds (user and system, every thread of the process that ran the
  whole mission in the study) times a core's power under load. The default, 4.4 W, is an AMD
  EPYC 7763's 280 W TDP over its 64 cores (AMD's data sheet): a server core; a flight computer
  would take longer at lower power, which this model does not capture.

Both constants are arguments of :func:`energy`, so a reader with better figures can redo the
arithmetic from runs.csv (``path_length_m``, ``cpu_s``).
"""

from __future__ import annotations

import os
import resource
from pathlib import Path

#: Joules a metre of driving costs, by platform (module docstring); None: not modelled.
DRIVE_J_PER_M: dict[str, float | None] = {"rover": 100.0 / 0.037, "flyer": None}
#: Watts of one busy CPU core (module docstring).
CORE_W = 280.0 / 64


def energy(platform: str, path_m: float, cpu_s: float, drive_j_per_m: float | None = None,
           core_w: float = CORE_W) -> dict[str, float | None]:
    """The run's energy in joules: ``drive_j`` (None where the platform has no figure),
    ``compute_j`` and ``total_j`` (None with the drive)."""
    per_m = DRIVE_J_PER_M.get(platform) if drive_j_per_m is None else drive_j_per_m
    drive = None if per_m is None else float(path_m) * per_m
    compute = float(cpu_s) * core_w
    return {"drive_j": drive, "compute_j": compute,
            "total_j": None if drive is None else drive + compute}


def _status_kb(field: str) -> int | None:
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith(field + ":"):
                return int(line.split()[1])
    except OSError:
        pass
    return None


class ProcessMeter:
    """CPU seconds and peak resident memory of this process from now on.

    Linux lets a process reset its own peak (writing 5 to /proc/self/clear_refs), so a worker
    that runs many missions one after another measures each one's peak; where it cannot, the
    peak is the process's since it started (``peak_scope`` says which)."""

    def __init__(self) -> None:
        self.peak_scope = "run"
        try:
            Path("/proc/self/clear_refs").write_text("5")
        except OSError:
            self.peak_scope = "process"
        t = os.times()
        self._cpu0 = t.user + t.system

    def cpu_s(self) -> float:
        t = os.times()
        return t.user + t.system - self._cpu0

    def peak_rss_mb(self) -> float:
        kb = _status_kb("VmHWM") if self.peak_scope == "run" else None
        if kb is None:
            kb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss  # KiB on Linux
        return kb / 1024
