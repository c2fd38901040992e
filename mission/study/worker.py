"""One run of a study, in a worker process: the mission in a temporary directory, renamed into
place when complete (the local pool's function, and the Dask cluster's)."""


from __future__ import annotations

import json
import logging
import os
import shutil
import time
from pathlib import Path

from mission.scoring.energy import energy
from rover_sim.catalog import resolve_scene
from rovergate.config import MissionConfig, from_dict


def init_worker(threads: int) -> None:
    import torch

    from rovergate.runtime import tune_allocator
    tune_allocator()
    torch.set_num_threads(threads)
    logging.getLogger().setLevel(logging.WARNING)  # the study's log is the progress bar


def run_one(job: tuple[dict, str, str]) -> tuple[str, float, str | None]:
    """Run one mission into a temporary directory and rename it into place when complete."""
    from mission.runtime.loop import run_in_process
    from mission.scoring.energy import ProcessMeter
    from mission.scoring.report import write_report
    from rovergate.config import save_config
    mission, run_id, runs_dir = job
    cfg = from_dict(MissionConfig, mission)
    final = Path(runs_dir) / run_id
    tmp = Path(runs_dir) / f".{run_id}.tmp-{os.getpid()}"
    t0 = time.perf_counter()
    try:
        resolve_scene(cfg.scene)
        cfg.out = tmp
        shutil.rmtree(tmp, ignore_errors=True)
        tmp.mkdir(parents=True)
        meter = ProcessMeter()
        record = run_in_process(cfg)
        cpu_s, peak_mb = meter.cpu_s(), meter.peak_rss_mb()
        cfg.out = final
        if record.recording:  # the bag moves with the run's directory
            record.recording["path"] = str(final / Path(record.recording["path"]).name)
        save_config(cfg, tmp / "config.json")
        write_report(cfg, record, tmp, plots=False)
        _add_costs(tmp / "metrics.json", cfg.platform, cpu_s, peak_mb, meter.peak_scope)
        os.replace(tmp, final)
    except Exception as exc:  # a failed run is reported, and the study goes on
        shutil.rmtree(tmp, ignore_errors=True)
        return run_id, time.perf_counter() - t0, f"{type(exc).__name__}: {exc}"
    return run_id, time.perf_counter() - t0, None




def _add_costs(path: Path, platform: str, cpu_s: float, peak_mb: float, scope: str) -> None:
    """The run's costs into its metrics.json (mission/scoring/energy.py): CPU seconds, the
    peak resident memory of the process that ran every module, and the energy estimate."""
    m = json.loads(path.read_text())
    m.update(cpu_s=cpu_s, peak_rss_mb=peak_mb, peak_rss_scope=scope,
             energy_j=energy(platform, m["path_length_m"], cpu_s))
    path.write_text(json.dumps(m, indent=2) + "\n")
