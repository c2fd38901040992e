"""The ``rovergate`` command: ``run`` a mission, or start one module (``sim``, ``mapper``,
``gate``, ``planner``) alone.

Every subcommand takes the mission config as flags (``--help`` lists them); ``--config FILE``
loads a saved ``config.json`` first, and flags given after it override it. The session flags
``--mode``, ``--connect``, ``--listen`` and ``--namespace`` join the Zenoh network.
"""

from __future__ import annotations

import signal
import sys
from collections.abc import Callable
from pathlib import Path

import tyro

from rovergate.config import MissionConfig, load_config

USAGE = """usage: rovergate COMMAND [--config FILE] [flags]

commands:
  run       run a mission (the process set over Zenoh, or --in-process) and write its report
  sim       start the simulator process alone
  mapper    start the mapper process alone
  gate      start the gate process alone
  planner   start the planner process alone
  scenes    list the scenes with their sizes and starts (--render DIR: a picture of each)
  train     reproduce the shipped occupancy model from nothing (about 35 min on 2 CPU cores)
  eval-model  precision / recall of the learned occupancy on held-out scenes
  study     the paper's controlled study: every (scene, start, condition, repetition) in
            parallel workers, resumable; writes runs.csv, table1.md, table2.md and plots
  ground    the ground station: shows and records the downlinked telemetry, sends commands
            (pause, resume, abort, set, condition, planner) up in the next contact window

`rovergate COMMAND --help` lists the flags."""


def _module_main(name: str) -> Callable[..., int]:
    def main(cfg: MissionConfig, resume_step: int = 0) -> int:
        from rover_sim.catalog import resolve_scene
        resolve_scene(cfg.scene)
        if name == "sim":
            from rover_sim.node import main as m
        elif name == "mapper":
            from mapper.node import main as m
        elif name == "gate":
            from gate.node import main as m
        else:
            from planner.node import main as m
        return m(cfg, resume_step)
    return main


def _run(cfg: MissionConfig) -> int:
    from mission.run import main
    return main(cfg)


COMMANDS: dict[str, Callable[..., int]] = {
    "run": _run, **{n: _module_main(n) for n in ("sim", "mapper", "gate", "planner")}}


def _aliases(args: list[str]) -> list[str]:
    """``--scene X`` is short for ``--scene.name X`` (as the docs write it)."""
    out = []
    for a in args:
        if a == "--scene":
            a = "--scene.name"
        elif a.startswith("--scene="):
            a = "--scene.name=" + a.split("=", 1)[1]
        out.append(a)
    return out


def _pop_resume_step(command: str, rest: list[str]) -> int:
    """``--resume-step N``: a module restarted by the mission takes up the loop at step N
    (the mission passes it; see mission/hub.py)."""
    if "--resume-step" not in rest:
        return 0
    i = rest.index("--resume-step")
    value = rest[i + 1] if i + 1 < len(rest) else ""
    if command == "run" or not value.isdigit():
        raise SystemExit("error: --resume-step takes a step number and is for the module "
                         "commands (sim, mapper, gate, planner), e.g. --resume-step 12")
    del rest[i:i + 2]
    return int(value)


def parse(argv: list[str]) -> tuple[str, MissionConfig, int]:
    """Split ``argv`` into the command, its resolved config and the step to resume at."""
    if not argv or argv[0] in ("-h", "--help") or argv[0] not in COMMANDS:
        if argv and argv[0] not in ("-h", "--help"):
            print(f"error: unknown command {argv[0]!r}", file=sys.stderr)
        print(USAGE, file=sys.stderr)
        raise SystemExit(0 if argv and argv[0] in ("-h", "--help") else 2)
    command, rest = argv[0], _aliases(list(argv[1:]))
    resume_step = _pop_resume_step(command, rest)
    default = MissionConfig()
    if "--config" in rest:
        i = rest.index("--config")
        if i + 1 >= len(rest):
            raise SystemExit("error: --config needs a file: --config runs/latest/config.json")
        default = load_config(Path(rest[i + 1]))
        del rest[i:i + 2]
    cfg = tyro.cli(MissionConfig, args=rest, default=default, prog=f"rovergate {command}",
                   description=COMMANDS[command].__doc__ or USAGE)
    return command, cfg, resume_step


def _interrupt(signum, frame) -> None:
    from rovergate.node import STOP
    STOP.set()


def main(argv: list[str] | None = None) -> None:
    argv = sys.argv[1:] if argv is None else argv
    if argv and argv[0] == "scenes":
        from rover_sim.overview import main as scenes_main
        raise SystemExit(scenes_main(argv[1:]))
    if argv and argv[0] == "train":
        from mapper.training import TrainConfig
        from mapper.training import main as train_main
        raise SystemExit(train_main(tyro.cli(TrainConfig, args=argv[1:],
                                             prog="rovergate train",
                                             description=TrainConfig.__doc__)))
    if argv and argv[0] == "eval-model":
        from mapper.evaluate import EvalModelConfig
        from mapper.evaluate import main as eval_main
        raise SystemExit(eval_main(tyro.cli(EvalModelConfig, args=argv[1:],
                                            prog="rovergate eval-model",
                                            description=EvalModelConfig.__doc__)))
    if argv and argv[0] == "study":
        from mission.study import StudyConfig, StudyFlagError, refuse_owned_mission_flags
        from mission.study import main as study_main
        try:
            refuse_owned_mission_flags(argv[1:])
        except StudyFlagError as exc:
            raise SystemExit(f"error: {exc}") from None
        raise SystemExit(study_main(tyro.cli(StudyConfig, args=argv[1:],
                                             prog="rovergate study",
                                             description=StudyConfig.__doc__)))
    # Ctrl-C and SIGTERM both mean: stop cleanly at the next wait (rovergate.node.STOP).
    # Installed explicitly, because a process started in the background may inherit an
    # ignored SIGINT.
    signal.signal(signal.SIGINT, _interrupt)
    signal.signal(signal.SIGTERM, _interrupt)
    if argv and argv[0] == "ground":
        from mission.ground import GroundConfig
        from mission.ground import main as ground_main
        raise SystemExit(ground_main(tyro.cli(GroundConfig, args=argv[1:],
                                              prog="rovergate ground",
                                              description=GroundConfig.__doc__)))
    command, cfg, resume_step = parse(argv)
    try:
        code = COMMANDS[command](cfg, resume_step) if resume_step else COMMANDS[command](cfg)
    except KeyboardInterrupt:
        code = 130
    raise SystemExit(code)


if __name__ == "__main__":
    main()
