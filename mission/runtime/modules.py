"""Which logic runs each module of the graph, and the module process's entry point
(``python -m mission.runtime.modules NAME --config FILE ...``, as the process set starts them,
or ``rovergate NAME ...``).

This is the composition root's table: :mod:`rovergate.graph` declares what each module
consumes and produces; here each name gets its logic class (transport-free, see
:mod:`rovergate.module`). Both transports build modules from it.
"""

from __future__ import annotations

import importlib
import logging
import os
import signal
import sys

from mission.runtime.flags import launched_config, mission_config
from rovergate.config import MissionConfig
from rovergate.errors import ConfigError, exit_code
from rovergate.module import STOP, Ask, ModuleLogic

#: The logic class of each launched module ("package.module:Class"), imported on use so that
#: a process imports only its own module's libraries.
LOGIC: dict[str, str] = {
    "sim": "rover_sim.logic:SimLogic",
    "mapper": "mapper.logic:MapperLogic",
    "gate": "gate.logic:GateLogic",
    "planner": "planner.logic:PlannerLogic",
}


def make_logic(name: str, cfg: MissionConfig, ask: Ask | None = None) -> ModuleLogic:
    """Build module ``name``'s logic for a mission (``ask`` answers its queryables)."""
    module, _, cls = LOGIC[name].partition(":")
    return getattr(importlib.import_module(module), cls)(cfg, ask)


def node_main(name: str, cfg: MissionConfig, resume_step: int | None = None) -> int:
    """A module as its own OS process: its logic on the Zenoh network until the mission ends
    (``rovergate sim|mapper|gate|planner``, as ``rovergate run`` starts them)."""
    from rovergate.graph import MODULES
    from rovergate.logs import init_logging
    from rovergate.node import ModuleNode

    log = init_logging(name)
    spec = MODULES[name]
    node = ModuleNode(spec, cfg.session, log)
    try:
        # The session opens first, so that the peers link while the logic loads.
        logic = make_logic(name, cfg, lambda topic: node.query(topic, cfg.ready_timeout_s))
    except BaseException:
        node.close()
        raise
    try:
        return node.run(logic, cfg.ready_timeout_s + cfg.step_timeout_s,
                        last_step=spec.last_step(cfg.steps), resume_step=resume_step)
    finally:
        logic.close()


def module_main(name: str, args: list[str], description: str = "") -> int:
    """Module ``name`` as its own process, configured by ``args`` (``--config FILE`` and flags
    over it; ``--resume-step N`` when the mission restarts it at step N). Exits the process
    when the module is done."""
    args = list(args)
    resume_step = None
    if "--resume-step" in args:  # a module restarted by the mission resumes at step N
        i = args.index("--resume-step")
        value = args[i + 1] if i + 1 < len(args) else ""
        if not value.isdigit():
            raise ConfigError("--resume-step takes a step number, e.g. --resume-step 12")
        resume_step = int(value)
        del args[i:i + 2]
    cfg = launched_config(args) or mission_config(name, args, description)
    if not cfg.scene.resolved:  # the mission passes a resolved config: no scene to load
        from rover_sim.catalog import resolve_scene
        resolve_scene(cfg.scene)
    code = node_main(name, cfg, resume_step)
    # The session is closed and the module's resources released: exit now. Tearing down
    # the interpreter (torch, trimesh, pybullet modules) took 0.5 to 1 s of every
    # mission's shutdown, and nothing is left for it to do.
    logging.shutdown()
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code)


def _interrupt(signum, frame) -> None:
    STOP.set()


def main(argv: list[str] | None = None) -> None:
    """``python -m mission.runtime.modules NAME ARGS``: one module's process."""
    from rovergate.runtime import tune_allocator
    argv = sys.argv[1:] if argv is None else argv
    if not argv or argv[0] not in LOGIC:
        print(f"error: give a module to run, one of: {', '.join(LOGIC)}", file=sys.stderr)
        raise SystemExit(2)
    # Ctrl-C and SIGTERM both mean: stop cleanly at the next wait (rovergate.module.STOP).
    signal.signal(signal.SIGINT, _interrupt)
    signal.signal(signal.SIGTERM, _interrupt)
    tune_allocator()
    raise SystemExit(exit_code(lambda: module_main(argv[0], argv[1:])))


if __name__ == "__main__":
    main()
