"""``rovergate run``: one mission, in the process set or in process, and its report."""

from __future__ import annotations

import json
import logging
import sys
from pathlib import Path

from tqdm import tqdm

from gate.conditions import get_condition
from mapper.mapper import mission_checkpoint
from mission.hub import MissionFailed, run_processes
from mission.loop import run_in_process
from mission.report import write_report
from rover_sim.catalog import resolve_scene
from rovergate.config import MissionConfig, save_config, to_dict
from rovergate.logs import init_logging
from rovergate.platform import check_platform


def check_runnable(cfg: MissionConfig) -> None:
    """Refuse, before anything starts, a mission that cannot run as configured."""
    check_platform(cfg.platform)
    get_condition(cfg.condition)
    mission_checkpoint(cfg)  # a missing or corrupt checkpoint stops the mission here
    if cfg.steps < 1:
        raise SystemExit(f"error: --steps must be at least 1, got {cfg.steps}")
    if cfg.in_process and cfg.planner.command:
        raise SystemExit("error: --planner.command runs a planner program, which needs the "
                         "process set; leave out --in-process")
    if cfg.contact.enabled and not cfg.in_process:
        from mission.contact import ContactPlan, ContactPlanError
        try:
            ContactPlan(cfg.contact)
        except ContactPlanError as exc:
            raise SystemExit(f"error: {exc}") from None


def main(cfg: MissionConfig) -> int:
    log = init_logging("mission")
    resolve_scene(cfg.scene)
    check_runnable(cfg)
    out = Path(cfg.out)
    out.mkdir(parents=True, exist_ok=True)
    save_config(cfg, out / "config.json")
    log.info("config (saved to %s):\n%s", out / "config.json", json.dumps(to_dict(cfg), indent=1))
    bar = tqdm(total=cfg.steps + 1, desc="mission", unit="step", disable=not cfg.progress,
               file=sys.stderr)

    def on_step(t: int, coverage: float) -> None:
        bar.update(1)
        bar.set_postfix(coverage=f"{coverage:.3f}")

    try:
        record = run_in_process(cfg, on_step) if cfg.in_process else run_processes(cfg, on_step)
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
    log.info("final coverage %.4f, AUC %.4f, %d collisions, %.1f m driven, %.1f s; report in %s",
             metrics["final_coverage"], metrics["auc"], metrics["collisions"],
             metrics["path_length_m"], metrics["wall_s"], out)
    logging.shutdown()
    return 0
