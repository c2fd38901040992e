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
import signal
import sys
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import tyro

from mission.runtime.flags import aliases, mission_config
from rovergate.config import MissionConfig
from rovergate.errors import ConfigError, exit_code
from rovergate.graph import LAUNCHED
from rovergate.module import STOP
from rovergate.runtime import tune_allocator


@dataclass(frozen=True)
class Command:
    """One subcommand: its help line, what reads its arguments into a configuration (a bad
    flag exits 2 with tyro's message, a bad value raises ConfigError) and what runs that."""

    help: str
    parse: Callable[[list[str]], Any]
    run: Callable[[Any], int]

    def main(self, args: list[str]) -> int:
        return self.run(self.parse(args))


def parse(argv: list[str]) -> Any:
    """What ``rovergate ARGV`` would run, read but not run: the docs' test checks every
    command the manual writes with it."""
    if not argv or argv[0] not in COMMANDS:
        raise ConfigError(f"unknown command {argv[:1]}; choose one of: {', '.join(COMMANDS)}")
    return COMMANDS[argv[0]].parse(list(argv[1:]))


def _parse_run(args: list[str]) -> Any:
    """``rovergate run [MISSION.toml] [flags]``: a mission file first, flags over it."""
    if args and not args[0].startswith("-"):
        from mission.script import load_script
        script = load_script(Path(args[0]))
        if any(a == "--config" or a.startswith("--config=") for a in args):
            raise ConfigError("give a mission file or --config FILE, not both")
        cfg = tyro.cli(MissionConfig, args=aliases(args[1:]), default=script.config,
                       prog="rovergate run MISSION.toml", description=COMMANDS["run"].help)
        return dataclasses.replace(script, config=cfg)
    return mission_config("run", args, COMMANDS["run"].help)


def _run(parsed: Any) -> int:
    if isinstance(parsed, MissionConfig):
        from mission.run import main
        return main(parsed)
    from mission.script import run_script
    return run_script(parsed)


def _module(name: str) -> Command:
    def run(args: list[str]) -> int:
        from mission.runtime.modules import module_main
        return module_main(name, args, COMMANDS[name].help)
    # The module process reads its own arguments (a launched module's are the mission's).
    return Command(f"start the {name} module alone (as `rovergate run` does)", list, run)


def _typed(prog: str, help: str, load: Callable[[], tuple[type, Callable[[Any], int]]],
           check: Callable[[list[str]], list[str] | None] | None = None) -> Command:
    """A subcommand whose flags tyro generates from a config class (imported on use).
    ``check`` may refuse the arguments, or return them rewritten."""
    def parse(args: list[str]) -> Any:
        if check is not None:
            args = check(args) or args
        cls, _ = load()
        return tyro.cli(cls, args=args, prog=f"rovergate {prog}", description=cls.__doc__)
    return Command(help, parse, lambda cfg: load()[1](cfg))


def _scenes():
    from rover_sim.overview import ScenesConfig, main
    return ScenesConfig, main


def _train():
    from mission.learning.training import TrainConfig, main
    return TrainConfig, main


def _eval_model():
    from mission.learning.evaluate import EvalModelConfig, main
    return EvalModelConfig, main


def _study():
    from mission.study.runner import main
    from mission.study.spec import StudyConfig
    return StudyConfig, main


def _study_args(args: list[str]) -> list[str]:
    """``--mission.X`` for what the study sets itself is refused, not silently ignored; a
    ``--preset`` becomes its flags, placed before the ones given (which win)."""
    from mission.study.spec import preset_args, refuse_owned_mission_flags
    refuse_owned_mission_flags(args)
    return preset_args(args)


def _replay():
    from ecosystem.replay import ReplayConfig, main

    def load_scene(scene):  # imported only when the view shows the scene
        from rover_sim.catalog import load_scene
        return load_scene(scene)
    return ReplayConfig, lambda cfg: main(cfg, load_scene)


def _credentials():
    from mission.link.credentials import CredentialsConfig, main
    return CredentialsConfig, main


def _ground():
    from mission.link.ground import GroundConfig, main
    return GroundConfig, main


COMMANDS: dict[str, Command] = {
    "run": Command("run a mission (the process set over Zenoh, or --in-process) and write "
                   "its report; `run MISSION.toml` runs a mission file and its timeline",
                   _parse_run, _run),
    **{name: _module(name) for name in LAUNCHED},
    "scenes": _typed("scenes", "list the scenes with their sizes and starts (--render DIR: a "
                     "picture of each)", _scenes),
    "train": _typed("train", "reproduce the shipped occupancy model from nothing (about 35 min "
                    "on 2 CPU cores)", _train),
    "eval-model": _typed("eval-model", "precision / recall of the learned occupancy on "
                         "held-out scenes", _eval_model),
    "replay": _typed("replay", "publish a recorded mission (OUT/bag) again over Zenoh, on the "
                     "keys it was recorded from, at its pace or --speed", _replay),
    "study": _typed("study", "the paper's controlled study: every (scene, start, condition, "
                    "repetition) in parallel workers, resumable; writes runs.csv, table1.md, "
                    "table2.md and plots", _study, _study_args),
    "ground": _typed("ground", "the ground station: shows and records the downlinked "
                     "telemetry, sends commands (pause, resume, abort, set, condition, "
                     "planner) up in the next contact window", _ground),
    "credentials": _typed("credentials", "create the ground link's certificates (a CA, the "
                          "rover's, a station's) for mutual TLS", _credentials),
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
    raise SystemExit(exit_code(lambda: COMMANDS[argv[0]].main(list(argv[1:]))))


if __name__ == "__main__":
    main()
