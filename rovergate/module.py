"""The contract between a module's logic and whatever carries its messages.

A module's logic (``rover_sim/logic.py``, ``mapper/logic.py``, ``gate/logic.py``,
``planner/logic.py``) implements :class:`ModuleLogic`: given the inputs of one step, as declared
for it in :mod:`rovergate.graph`, it returns the messages it publishes and the time each stage
took. It never touches a transport. Two transports drive the same logic: direct calls in one
process (:class:`mission.runtime.transport.InProcessTransport`), and Zenoh, one OS process per
module (:class:`rovergate.node.ModuleNode`).

Values are the plain data of :mod:`rovergate.types`: what :func:`rovergate.messages.encode`
takes for a topic (``(step, array)`` for depth, camera info, poses and clouds; a dataclass with
its ``step`` for the rest), and what a reader's handler receives is that value without the
step (see :func:`rovergate.messages.stamped`).
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, ClassVar, Protocol

from rovergate.graph import Module

#: Set by the command line's SIGINT/SIGTERM handler: every wait polls it and stops cleanly at
#: a safe point (a module process, the mission loop in either transport).
STOP = threading.Event()

#: How a module asks for a queryable's value (the gate, for the reference occupancy): the
#: transport answers, from the simulator in one process or over Zenoh.
Ask = Callable[[str], Any]


@dataclass
class StepOutput:
    """What a module produced for one step."""

    messages: list[tuple[str, Any]] = field(default_factory=list)
    """``(topic, value)`` in the order they are published."""
    stages: dict[str, float] = field(default_factory=dict)
    """Compute seconds per timing stage (publishing excluded)."""


class ModuleLogic(Protocol):
    """One module's behaviour, free of any transport.

    A module is a deterministic function of its input streams: :meth:`restore` with the
    ``replay`` inputs of every past step rebuilds exactly the state that :meth:`handle` had
    built, which is how a restarted module recovers (the mission journals those inputs).
    """

    spec: ClassVar[Module]

    def handle(self, step: int, inputs: dict[str, Any]) -> StepOutput:
        """The outputs of ``step`` from its inputs (keyed by the names in ``spec.inputs``;
        an input of lag L is ``None`` for steps before L)."""
        ...

    def restore(self, step: int, inputs: dict[str, Any]) -> None:
        """Take up past step ``step`` from its ``spec.replay`` inputs, publishing nothing."""
        ...

    def serve(self, topic: str) -> Any:
        """The value of a queryable in ``spec.serves``."""
        ...

    def close(self) -> None:
        """Release what the module holds (the simulator's pybullet world)."""
        ...


class LogicDefaults:
    """Defaults of :class:`ModuleLogic`: nothing to replay (a module that keeps no state
    between steps; a stateful one overrides :meth:`restore`), nothing served, nothing to
    release."""

    def restore(self, step: int, inputs: dict[str, Any]) -> None:
        return None

    def serve(self, topic: str) -> Any:
        raise KeyError(topic)

    def close(self) -> None:
        return None
