"""Which logic runs each module of the graph, and the module process's entry point.

This is the composition root's table: :mod:`rovergate.graph` declares what each module
consumes and produces; here each name gets its logic class (transport-free, see
:mod:`rovergate.module`). Both transports build modules from it.
"""

from __future__ import annotations

import importlib

from rovergate.config import MissionConfig
from rovergate.module import Ask, ModuleLogic

#: The logic class of each launched module ("package.module:Class"), imported on use so that
#: a process imports only its own module's libraries.
LOGIC: dict[str, str] = {
    "sim": "rover_sim.node:SimNode",
    "mapper": "mapper.node:MapperNode",
    "gate": "gate.node:GateNode",
    "planner": "planner.node:PlannerNode",
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
