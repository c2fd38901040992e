"""``rovergate study``: the paper's controlled study, every run closed loop from scratch.

Each (scene, start, condition, repetition) is one mission of ``--steps`` planning steps, run in
one process (:func:`mission.runtime.loop.run_in_process`, which gives the same numbers as the
process set) by a pool of worker processes, one torch thread each. Repetition r runs with seed r, so
repetitions differ in the planner's candidate draws and OMPL's sampling, and the same seed
gives the same run in any worker.

Layout of ``--out``::

    study.json          the study's settings (a re-run must match them)
    runs/<id>/          one finished run: metrics.json, coverage.csv, config.json
    runs.csv            one row per finished run
    table1.md           the paper's Table 1 layout over every repetition, bootstrap 95% CIs over
                        starts, a placebo row (learned against itself), failure modes
    table2.md           the paper's Table 2 layout: learned against gated, every start, with
                        sign-flip p-values, Holm correction, a sign test, the paper's selection
    summary.json        the tables' figures, the study's wall time and per-stage medians
    coverage_<condition>.png  every run's coverage curve, with the mean
    coverage_curves.csv every run's per-step coverage, one row per run

A study of cells (``--platform flyer rover``, ``--profiles ...``, or ``--preset validation``)
runs every (platform, sensing profile) as a cell: run ids start with ``<platform>-<profile>-``,
each cell's tables (the layout above, without study.json) go to ``<platform>-<profile>/``, and
the study's own outputs are :mod:`mission.study.validation`'s: runs.csv over every cell,
validation.md, validation_*.png and summary.json.

A held-out test (``--select-from DIR --seeds 3..12``, :mod:`mission.study.heldout`) runs only
the starts the paper's rule selects from the study in DIR, declares them in ``selection.json``
before any run, and adds ``heldout.md``: the new seeds' effects beside the selected ones.

Resuming: a run directory appears only complete (it is written under a temporary name and
renamed), so a re-run with the same ``--out`` skips every finished run, and a killed study
loses at most the runs that were in flight.
"""

from __future__ import annotations

import json
import logging
import multiprocessing as mp
import os
import shutil
import signal
import sys
import time
from pathlib import Path

from tqdm import tqdm

from mission.study.spec import (
    StudyConfig,
    cells,
    check_study,
    mission_config,
    parse_seeds,
    run_specs,
)
from mission.study.worker import init_worker, run_one
from rovergate.config import MissionConfig, from_dict, to_dict
from rovergate.errors import ConfigError
from rovergate.logs import init_logging

log = logging.getLogger("rovergate.study")


# ----------------------------------------------------------------------------- the study

def _settings(cfg: StudyConfig) -> dict:
    """What must match for a study directory to be resumed."""
    d = to_dict(cfg)
    for k in ("workers", "torch_threads", "out", "bootstrap", "progress", "preset", "record",
              "cluster", "tables_only"):
        d.pop(k)
    d["mission"] = _without_recording(d["mission"])
    # A study of one platform, nominal, saves its settings as studies did before cells.
    if not cells(cfg):
        d["platform"] = cfg.platform[0]
        d.pop("profiles")
    return d


def _normalised(saved: dict | None) -> dict | None:
    """Saved settings with the mission's settings that did not exist when they were saved
    filled in at their defaults (what those runs ran with), so that a study resumes across a
    release that added a setting."""
    if not isinstance(saved, dict) or not isinstance(saved.get("mission"), dict):
        return saved
    try:
        mission = to_dict(from_dict(MissionConfig, saved["mission"]))
    except Exception:  # not ours to judge here: it simply does not match
        return saved
    # Study settings added since (--seeds, --select-from): those runs had their defaults.
    added = {k: v for k, v in _settings(StudyConfig()).items()
             if k not in saved and k not in ("platform", "profiles")}
    return {**added, **saved, "mission": _without_recording(mission)}


#: Mission settings that change what is written or served beside a run, never its figures.
_OUTPUTS = ("record", "record_compression", "viz", "viz_host", "viz_port", "ros2",
            "ros2_router", "ros2_domain")


def _without_recording(mission: dict) -> dict:
    return {k: v for k, v in mission.items() if k not in _OUTPUTS}


def _results(cfg: StudyConfig, jobs: list, runs_dir: Path):
    """(run id, seconds, error) of every job as it finishes: from a local pool of
    ``cfg.workers`` processes, or from the Dask cluster at ``cfg.cluster``."""
    if cfg.cluster:
        from mission.study.cluster import cluster_results
        yield from cluster_results(cfg.cluster, jobs, cfg.torch_threads, runs_dir)
        return
    ctx = mp.get_context("spawn")
    with ctx.Pool(cfg.workers, initializer=init_worker,
                  initargs=(cfg.torch_threads,)) as pool:
        yield from pool.imap_unordered(run_one, jobs)


def _terminate(signum, frame) -> None:
    raise KeyboardInterrupt  # leaving the pool's context terminates its workers


def _tables_only(cfg: StudyConfig, out: Path, specs: list, sessions: list) -> int:
    """--tables-only: the tables again from OUT/runs.csv and OUT/coverage_curves.csv."""
    if cells(cfg):
        raise ConfigError("--tables-only rewrites a study of one platform and profile; a study "
                          "of cells needs its run directories (re-run it with the same --out)")
    from mission.study.tables import rows_from_csv, write_tables
    loaded = rows_from_csv(out)
    summary = write_tables(cfg, specs, out, sessions=sessions, loaded=loaded)
    if cfg.select_from:
        from mission.study.heldout import SELECTION_FILE, declare, parse_seeds, write_heldout
        if not (out / SELECTION_FILE).exists():  # a selection is declared before runs, only
            raise ConfigError(f"--tables-only: {out / SELECTION_FILE} is missing; a held-out "
                              "study's selection is declared when it starts, not afterwards")
        decl = declare(cfg.select_from, out, parse_seeds(cfg.seeds))
        write_heldout(cfg, specs, out, decl, summary, rows=loaded[0])
    log.info("tables of %d runs rewritten in %s from runs.csv and coverage_curves.csv",
             len(loaded[0]), out)
    return 0


def main(cfg: StudyConfig) -> int:
    init_logging("study")
    signal.signal(signal.SIGTERM, _terminate)
    cfg = check_study(cfg)
    only = None
    if cfg.select_from:  # refused before anything is written
        from mission.study.heldout import check
        only = check(cfg)
    out = Path(cfg.out)
    runs_dir = out / "runs"
    runs_dir.mkdir(parents=True, exist_ok=True)
    settings_path = out / "study.json"
    settings = _settings(cfg)
    if settings_path.exists():
        try:
            saved = json.loads(settings_path.read_text())
        except ValueError:
            raise ConfigError(f"{settings_path} is not valid JSON; delete it, or give "
                              "--out a new directory") from None
        if _normalised(saved.get("settings")) != settings:
            raise ConfigError(f"{out} holds a study with other settings; give --out a "
                              f"new directory, or delete {out} to start this one there")
        sessions = saved.get("sessions", [])
    else:
        sessions = []
    if cfg.tables_only:
        return _tables_only(cfg, out, run_specs(cfg, only), sessions)
    for leftover in runs_dir.glob(".*.tmp-*"):  # runs that were in flight when killed
        shutil.rmtree(leftover, ignore_errors=True)

    decl = None
    if cfg.select_from:  # declared before any run, and checked again on every resume
        from mission.study.heldout import declare
        decl = declare(cfg.select_from, out, parse_seeds(cfg.seeds))
        log.info("held-out test: %d starts selected from %s (%s), seeds %s: see %s",
                 len(decl["starts"]), cfg.select_from, ", ".join(decl["starts"]), cfg.seeds,
                 out / "selection.json")
    specs = run_specs(cfg, only)
    done = {p.name for p in runs_dir.iterdir() if (p / "metrics.json").exists()}
    todo = [s for s in specs if s.id not in done]
    log.info("%d runs: %d finished before, %d to run on %s (out: %s)", len(specs),
             len(specs) - len(todo), len(todo),
             f"the Dask cluster at {cfg.cluster}" if cfg.cluster else f"{cfg.workers} workers",
             out)
    if cfg.filter_reps > cfg.reps and not cfg.seeds:
        log.info("`learned` and the gates run %d times a start (--filter-reps %d, for Table 2), "
                 "the other conditions %d (--reps)", cfg.filter_reps, cfg.filter_reps, cfg.reps)
    t0 = time.perf_counter()
    session = {"started": time.strftime("%Y-%m-%d %H:%M:%S"), "runs": 0, "wall_s": 0.0,
               "workers": cfg.workers, **({"cluster": cfg.cluster} if cfg.cluster else {})}
    sessions.append(session)

    def save_progress() -> None:
        # Written whole or not at all: a study killed mid-write must still resume.
        session["wall_s"] = time.perf_counter() - t0
        tmp = settings_path.with_name(f".{settings_path.name}.tmp")
        tmp.write_text(json.dumps({"settings": settings, "sessions": sessions}, indent=1)
                       + "\n")
        os.replace(tmp, settings_path)

    save_progress()
    failures: list[tuple[str, str]] = []
    if todo:
        jobs = [(to_dict(mission_config(cfg, s, runs_dir / s.id)), s.id, str(runs_dir))
                for s in todo]
        bar = tqdm(total=len(specs), initial=len(specs) - len(todo), desc="study", unit="run",
                   disable=not cfg.progress, file=sys.stderr, smoothing=0.05)
        try:
            for run_id, seconds, error in _results(cfg, jobs, runs_dir):
                bar.update(1)
                if error:
                    failures.append((run_id, error))
                    log.error("run %s failed after %.0f s: %s", run_id, seconds, error)
                else:
                    session["runs"] += 1
                    bar.set_postfix_str(f"{run_id} {seconds:.0f}s")
                    log.info("run %s finished in %.0f s", run_id, seconds)
                save_progress()
        except KeyboardInterrupt:
            bar.close()
            save_progress()
            log.error("stopped; the finished runs are kept: re-run the same command to resume")
            return 130
        bar.close()
    save_progress()

    if cells(cfg):
        from mission.study.validation import write_validation
        summary = write_validation(cfg, specs, out)
    else:
        from mission.study.tables import write_tables
        summary = write_tables(cfg, specs, out)
    if decl is not None:
        from mission.study.heldout import write_heldout
        summary = write_heldout(cfg, specs, out, decl, summary)
    wall = sum(s["wall_s"] for s in sessions)
    log.info("study: %d runs in %.1f min of wall time over %d session(s); tables in %s",
             summary["runs"], wall / 60, len(sessions), out)
    if failures:
        log.error("%d runs failed (re-run the same command to retry them): %s", len(failures),
                  ", ".join(r for r, _ in failures))
        return 1
    return 0
