"""``rovergate run``: one mission, in the process set or in process, and its report."""

from __future__ import annotations

import dataclasses
import fcntl
import json
import logging
import os
import sys
from collections.abc import Callable
from pathlib import Path
from typing import IO

from tqdm import tqdm

from mapper.mapper import mission_checkpoint
from mission.runtime.checkpoint import LoopState
from mission.runtime.checkpoint import load as load_checkpoint
from mission.runtime.checkpoint import remove as remove_checkpoint
from mission.runtime.loop import run_in_process, run_processes
from mission.scoring.report import write_report
from planner.planner import planner_class, planner_name, planner_names
from rover_sim.catalog import load_scene, resolve_scene
from rovergate.conditions import get_condition
from rovergate.config import (
    MissionConfig,
    changed_settings,
    check_values,
    planner_programs,
    save_config,
    to_dict,
)
from rovergate.errors import ConfigError, MissionFailed, UnknownNameError
from rovergate.logs import init_logging, plural
from rovergate.platforms import get_platform


def check_runnable(cfg: MissionConfig) -> None:
    """Refuse, before anything starts, a mission that cannot run as configured: every name
    resolves, every count and limit is in range, the checkpoint loads, the contact plan is
    valid. Raises :class:`ConfigError` (or :class:`UnknownNameError`) with one line."""
    get_platform(cfg.platform)
    get_condition(cfg.condition)
    resolve_scene(cfg.scene)
    scene = load_scene(cfg.scene)
    if cfg.start not in scene.starts:
        raise UnknownNameError(f"scene {scene.name!r} has no start {cfg.start!r}; choose one "
                               f"of: {', '.join(scene.starts)} (--start)")
    if not cfg.planner.command:
        planner_class(planner_name(cfg))  # an unknown name, or one that does not load
    check_values(cfg)
    for name in planner_programs(cfg.planner):
        if name in ("auto", "cmd", *planner_names()):
            raise ConfigError(f"--planner.programs: {name!r} is the name of a built-in or "
                              "installed planner; give the program another name")
    mission_checkpoint(cfg)  # a bad --mapper.prediction or checkpoint stops the mission here
    if cfg.in_process and cfg.planner.command:
        raise ConfigError("--planner.command runs a planner program, which needs the "
                          "process set; leave out --in-process")
    if cfg.contact.enabled and not cfg.in_process:
        from mission.link.bridge import check_ground_endpoints, ground_tls
        from mission.link.contact import ContactPlan, ContactPlanError
        tls = ground_tls(cfg.contact)
        if tls is not None:
            tls.check()
        check_ground_endpoints(tuple(cfg.contact.ground_listen), tls is not None,
                               tuple(cfg.contact.ground_stations))
        try:
            ContactPlan(cfg.contact).end_of_mission(cfg.steps, cfg.contact.drain_steps)
        except ContactPlanError as exc:
            raise ConfigError(str(exc)) from None


def resumed_config(cfg: MissionConfig) -> tuple[MissionConfig, LoopState]:
    """``--resume``: the configuration and state of the mission in ``cfg.out`` (raises
    ConfigError if the command line sets anything else, or there is nothing to resume)."""
    extra = changed_settings(cfg, MissionConfig(out=cfg.out, resume=True, progress=cfg.progress))
    if extra:
        raise ConfigError("--resume carries on the mission in --out as it was configured; "
                          "leave out " + ", ".join("--" + k.replace("_", "-") for k in extra))
    state = load_checkpoint(Path(cfg.out))
    resumed = dataclasses.replace(state.cfg, out=cfg.out, progress=cfg.progress, resume=True)
    if resumed.in_process:
        raise ConfigError("--resume: the mission in --out ran in process; only a process-set "
                          "mission keeps a checkpoint")
    return resumed, state


LOCK = ".mission.lock"
"""Held (flock) by the mission manager using a directory, for as long as its process lives:
the kernel releases it when the process ends, SIGKILL included."""


def hold_directory(out: Path) -> IO[str]:
    """Take ``out`` for this process, or raise ConfigError naming the manager that has it (a
    second mission, or a --resume of a mission still running, would share its journal)."""
    out.mkdir(parents=True, exist_ok=True)
    f = open(out / LOCK, "a+")  # noqa: SIM115 -- held until the process ends
    try:
        fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        f.seek(0)
        holder = f.read().strip() or "?"
        f.close()
        raise ConfigError(f"another mission manager (pid {holder}) is running in {out}; wait "
                          "for it to end, or give this mission another --out") from None
    f.seek(0)
    f.truncate()
    f.write(f"{os.getpid()}\n")
    f.flush()
    return f


def main(cfg: MissionConfig, on_link: Callable[[], None] | None = None) -> int:
    """Run one mission as configured and write its report under ``cfg.out``. ``on_link``
    (process set, with the ground link) is called once the link's endpoint is up and
    ``OUT/ground.json`` names it (a mission script starts its ground station there)."""
    log = init_logging("mission")
    lock = hold_directory(Path(cfg.out))  # noqa: F841 -- held until the process ends
    state = None
    if cfg.resume:
        cfg, state = resumed_config(cfg)
    check_runnable(cfg)
    out = Path(cfg.out)
    if state is None:
        remove_checkpoint(out)  # another mission's, in the same --out
        save_config(cfg, out / "config.json")
        log.info("%s, %s, %s on %s/%s, %s; configuration in %s (`rovergate run --config "
                 "%s` runs it again)", "in process" if cfg.in_process else "process set",
                 cfg.platform, cfg.condition, cfg.scene.name, cfg.start, plural(cfg.steps, "step"),
                 out / "config.json", out / "config.json")
        log.debug("config:\n%s", json.dumps(to_dict(cfg), indent=1))
    else:
        log.info("resuming the mission in %s at step %d (checkpoint of %s)", out, state.step,
                 state.saved_at)
    bar = tqdm(total=cfg.steps + 1, desc="mission", unit="step", disable=not cfg.progress,
               file=sys.stderr, initial=state.step if state else 0)

    def on_step(t: int, coverage: float) -> None:
        bar.update(1)
        bar.set_postfix(coverage=f"{coverage:.3f}")

    try:
        record = (run_in_process(cfg, on_step) if cfg.in_process
                  else run_processes(cfg, on_step, state, on_link))
    except MissionFailed as exc:
        bar.close()
        log.error("mission failed: %s", exc)
        return 1
    except KeyboardInterrupt:
        bar.close()
        log.error("interrupted; every module was stopped")
        return 130
    bar.close()
    metrics = write_report(cfg, record, out)
    log.info("final coverage %.4f, AUC %.4f, %s, %.1f m driven, %.1f s", metrics["final_coverage"],
             metrics["auc"], plural(metrics["collisions"], "collision"), metrics["path_length_m"],
             metrics["wall_s"])
    files = ["metrics.json", "coverage.csv", "coverage.png", "map_topdown.png", "config.json"]
    log.info("report in %s: %s%s", out, ", ".join(f for f in files if (out / f).exists()),
             f"; the bag in {record.recording['path']} (`rovergate replay "
             f"{record.recording['path']} --viz` plays it to Foxglove)" if record.recording else "")
    logging.shutdown()
    return 0
