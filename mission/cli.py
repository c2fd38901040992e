"""The ``rovergate`` command: the composition root that wires the packages into programs.

Every subcommand is a config dataclass and a ``main(config)``; tyro generates its flags and
``--help`` from the dataclass and its field docstrings. ``run`` and the module commands
(``sim``, ``mapper``, ``gate``, ``planner``: one module as its own process, as ``rovergate run``
starts them) take the mission's config; ``--config FILE`` loads a saved ``config.json`` first,
and flags given after it override it.

Library code raises typed errors (:mod:`rovergate.errors`); only this module turns them into
one line on stderr and an exit code: 2 for a setting that cannot be used, 1 for a mission that
failed, 130 when interrupted.
"""

from __future__ import annotations

import dataclasses
import logging
import os
import signal
import sys
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import tyro

from rovergate.config import MissionConfig, load_config
from rovergate.errors import ConfigError, RovergateError
from rovergate.graph import LAUNCHED
from rovergate.module import STOP
from rovergate.runtime import tune_allocator


@dataclass(frozen=True)
class Command:
    """One subcommand: its help line and what parses and runs it."""

    help: str
    main: Callable[[list[str]], int]


def _mission_config(command: str, args: list[str]) -> MissionConfig:
    """The mission config of ``args``: ``--config FILE`` first, then the flags over it."""
    args = _aliases(args)
    default = MissionConfig()
    if "--config" in args:
        i = args.index("--config")
        if i + 1 >= len(args):
            raise ConfigError("--config needs a file: --config runs/latest/config.json")
        default = load_config(Path(args[i + 1]))
        del args[i:i + 2]
    return tyro.cli(MissionConfig, args=args, default=default, prog=f"rovergate {command}",
                    description=COMMANDS[command].help)


#: The session flags ``rovergate run`` gives the modules it starts (``--config FILE`` before them).
_LAUNCH_FLAGS = {"--mode": 1, "--connect": None, "--listen": None, "--namespace": 1,
                 "--wait-for-peers": 1}


def _launched_config(args: list[str]) -> MissionConfig | None:
    """The config of a module's command line as ``rovergate run`` writes it (``--config FILE``
    then only session flags), read without tyro: building tyro's parser of the whole mission
    config cost each module 0.1 to 0.2 s of the process set's start-up. Any other command line
    (a user's own flags) returns None and goes to tyro, which gives the same config."""
    if len(args) < 2 or args[0] != "--config":
        return None
    given: dict[str, list[str]] = {}
    flag = None
    for a in args[2:]:
        if a.startswith("--"):
            if a not in _LAUNCH_FLAGS or a in given:
                return None
            flag = a
            given[a] = []
        elif flag is None:
            return None
        else:
            given[flag].append(a)
    if any(n is not None and len(given[f]) != n for f, n in _LAUNCH_FLAGS.items() if f in given):
        return None
    cfg = load_config(Path(args[1]))
    session = cfg.session
    if "--mode" in given:
        if given["--mode"][0] not in ("peer", "client", "router"):
            return None
        session = dataclasses.replace(session, mode=given["--mode"][0])
    for f, field in (("--connect", "connect"), ("--listen", "listen")):
        if f in given:
            session = dataclasses.replace(session, **{field: tuple(given[f])})
    if "--namespace" in given:
        session = dataclasses.replace(session, namespace=given["--namespace"][0])
    if "--wait-for-peers" in given:
        if not given["--wait-for-peers"][0].isdigit():
            return None
        session = dataclasses.replace(session, wait_for_peers=int(given["--wait-for-peers"][0]))
    return dataclasses.replace(cfg, session=session)


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


def _run(args: list[str]) -> int:
    """``rovergate run [MISSION.toml] [flags]``: a mission file first, flags over it."""
    if args and not args[0].startswith("-"):
        from mission.script import load_script, run_script
        script = load_script(Path(args[0]))
        if any(a == "--config" or a.startswith("--config=") for a in args):
            raise ConfigError("give a mission file or --config FILE, not both")
        cfg = tyro.cli(MissionConfig, args=_aliases(args[1:]), default=script.config,
                       prog="rovergate run MISSION.toml", description=COMMANDS["run"].help)
        return run_script(dataclasses.replace(script, config=cfg))
    from mission.run import main
    return main(_mission_config("run", args))


def _module(name: str) -> Callable[[list[str]], int]:
    def main(args: list[str]) -> int:
        args = list(args)
        resume_step = None
        if "--resume-step" in args:  # a module restarted by the mission resumes at step N
            i = args.index("--resume-step")
            value = args[i + 1] if i + 1 < len(args) else ""
            if not value.isdigit():
                raise ConfigError("--resume-step takes a step number, e.g. --resume-step 12")
            resume_step = int(value)
            del args[i:i + 2]
        cfg = _launched_config(args) or _mission_config(name, args)
        if not cfg.scene.resolved:  # the mission passes a resolved config: no scene to load
            from rover_sim.catalog import resolve_scene
            resolve_scene(cfg.scene)
        from mission.modules import node_main
        code = node_main(name, cfg, resume_step)
        # The session is closed and the module's resources released: exit now. Tearing down
        # the interpreter (torch, trimesh, pybullet modules) took 0.5 to 1 s of every
        # mission's shutdown, and nothing is left for it to do.
        logging.shutdown()
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(code)
    return main


def _typed(prog: str, load: Callable[[], tuple[type, Callable[[Any], int]]],
           check: Callable[[list[str]], list[str] | None] | None = None
           ) -> Callable[[list[str]], int]:
    """A subcommand whose flags tyro generates from a config class (imported on use).
    ``check`` may refuse the arguments, or return them rewritten."""
    def main(args: list[str]) -> int:
        if check is not None:
            args = check(args) or args
        cls, run = load()
        return run(tyro.cli(cls, args=args, prog=f"rovergate {prog}",
                            description=cls.__doc__))
    return main


def _scenes():
    from rover_sim.overview import ScenesConfig, main
    return ScenesConfig, main


def _train():
    from mapper.training import TrainConfig, main
    return TrainConfig, main


def _eval_model():
    from mapper.evaluate import EvalModelConfig, main
    return EvalModelConfig, main


def _study():
    from mission.study import StudyConfig, main
    return StudyConfig, main


def _study_args(args: list[str]) -> list[str]:
    """``--mission.X`` for what the study sets itself is refused, not silently ignored; a
    ``--preset`` becomes its flags, placed before the ones given (which win)."""
    from mission.study import preset_args, refuse_owned_mission_flags
    refuse_owned_mission_flags(args)
    return preset_args(args)


def _replay():
    from ecosystem.replay import ReplayConfig, main
    return ReplayConfig, main


def _credentials():
    from mission.credentials import CredentialsConfig, main
    return CredentialsConfig, main


def _ground():
    from mission.ground import GroundConfig, main
    return GroundConfig, main


COMMANDS: dict[str, Command] = {
    "run": Command("run a mission (the process set over Zenoh, or --in-process) and write "
                   "its report; `run MISSION.toml` runs a mission file and its timeline",
                   _run),
    **{name: Command(f"start the {name} module alone (as `rovergate run` does)", _module(name))
       for name in LAUNCHED},
    "scenes": Command("list the scenes with their sizes and starts (--render DIR: a picture "
                      "of each)", _typed("scenes", _scenes)),
    "train": Command("reproduce the shipped occupancy model from nothing (about 35 min on 2 "
                     "CPU cores)", _typed("train", _train)),
    "eval-model": Command("precision / recall of the learned occupancy on held-out scenes",
                          _typed("eval-model", _eval_model)),
    "replay": Command("publish a recorded mission (OUT/bag) again over Zenoh, on the keys it "
                      "was recorded from, at its pace or --speed", _typed("replay", _replay)),
    "study": Command("the paper's controlled study: every (scene, start, condition, "
                     "repetition) in parallel workers, resumable; writes runs.csv, table1.md, "
                     "table2.md and plots", _typed("study", _study, _study_args)),
    "ground": Command("the ground station: shows and records the downlinked telemetry, sends "
                      "commands (pause, resume, abort, set, condition, planner) up in the "
                      "next contact window", _typed("ground", _ground)),
    "credentials": Command("create the ground link's certificates (a CA, the rover's, a "
                           "station's) for mutual TLS", _typed("credentials", _credentials)),
}


def usage() -> str:
    lines = ["usage: rovergate COMMAND [flags]", "", "commands:"]
    lines += [f"  {name:<11} {c.help}" for name, c in COMMANDS.items()]
    lines += ["", "`rovergate COMMAND --help` lists the flags of a command."]
    return "\n".join(lines)


def _interrupt(signum, frame) -> None:
    STOP.set()


def main(argv: list[str] | None = None) -> None:
    argv = sys.argv[1:] if argv is None else argv
    if not argv or argv[0] in ("-h", "--help"):
        print(usage(), file=sys.stderr)
        raise SystemExit(0 if argv else 2)
    if argv[0] not in COMMANDS:
        print(f"error: unknown command {argv[0]!r}; choose one of: {', '.join(COMMANDS)}",
              file=sys.stderr)
        raise SystemExit(2)
    # Ctrl-C and SIGTERM both mean: stop cleanly at the next wait (rovergate.module.STOP).
    # Installed explicitly, because a process started in the background may inherit an
    # ignored SIGINT. The study has its own (it has worker processes to stop); training,
    # evaluation and the scene listing stop at once on KeyboardInterrupt.
    if argv[0] in ("run", "ground", "replay", *LAUNCHED):
        signal.signal(signal.SIGINT, _interrupt)
        signal.signal(signal.SIGTERM, _interrupt)
    tune_allocator()
    try:
        code = COMMANDS[argv[0]].main(list(argv[1:]))
    except ConfigError as exc:
        print(f"error: {exc}", file=sys.stderr)
        code = 2
    except RovergateError as exc:
        print(f"error: {exc}", file=sys.stderr)
        code = 1
    except KeyboardInterrupt:
        code = 130
    raise SystemExit(code)


if __name__ == "__main__":
    main()
