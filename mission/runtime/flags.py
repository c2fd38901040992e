"""A mission's configuration from a command line: ``--config FILE`` first, then flags over it
(tyro's parser of :class:`rovergate.config.MissionConfig`), and the quick read of the command
line ``rovergate run`` gives the modules it starts. Used by the command line
(:mod:`mission.cli`) and by every module process (:mod:`mission.runtime.modules`)."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import tyro

from rovergate.config import MissionConfig, load_config
from rovergate.errors import ConfigError


def mission_config(command: str, args: list[str], description: str = "") -> MissionConfig:
    """The mission config of ``args`` (``rovergate COMMAND``'s flags): ``--config FILE``
    first, then the flags over it."""
    args = aliases(args)
    default = MissionConfig()
    if "--config" in args:
        i = args.index("--config")
        if i + 1 >= len(args):
            raise ConfigError("--config needs a file: --config runs/latest/config.json")
        default = load_config(Path(args[i + 1]))
        del args[i:i + 2]
    return tyro.cli(MissionConfig, args=args, default=default, prog=f"rovergate {command}",
                    description=description)


#: The session flags ``rovergate run`` gives the modules it starts (``--config FILE`` before them).
LAUNCH_FLAGS = {"--mode": 1, "--connect": None, "--listen": None, "--namespace": 1,
                 "--wait-for-peers": 1}


def launched_config(args: list[str]) -> MissionConfig | None:
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
            if a not in LAUNCH_FLAGS or a in given:
                return None
            flag = a
            given[a] = []
        elif flag is None:
            return None
        else:
            given[flag].append(a)
    if any(n is not None and len(given[f]) != n for f, n in LAUNCH_FLAGS.items() if f in given):
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


def aliases(args: list[str]) -> list[str]:
    """``--scene X`` is short for ``--scene.name X`` (as the docs write it)."""
    out = []
    for a in args:
        if a == "--scene":
            a = "--scene.name"
        elif a.startswith("--scene="):
            a = "--scene.name=" + a.split("=", 1)[1]
        out.append(a)
    return out
