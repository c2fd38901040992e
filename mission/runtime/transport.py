"""What the mission loop drives: a transport that carries the graph's messages.

The loop (:func:`mission.runtime.loop.run_mission`) is written once, against :class:`Transport`: it
ticks the clock, receives its inputs of each step (declared as ``MODULES["mission"]`` in
:mod:`rovergate.graph`) and keeps the record. Two transports implement it:

- :class:`InProcessTransport` (here): every module's logic in this process, called directly
  and routed by the graph; no Zenoh.
- :class:`mission.runtime.process_set.ProcessSetTransport`: every module its own OS process, over
  Zenoh, with health checks and restarts.

Each module is a deterministic function of its inputs, so both give the same numbers to the
last digit.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, Protocol

import numpy as np

from rovergate.config import MissionConfig
from rovergate.errors import MissionFailed
from rovergate.graph import LAUNCHED, MODULES, consumers, producer
from rovergate.messages import encode, stamped
from rovergate.module import ModuleLogic
from rovergate.streams import INCREMENTAL, StreamEncoder
from rovergate.types import CloudUpdate, MissionStatus, StepTiming

if TYPE_CHECKING:
    from rovergate.taps import Taps


class Transport(Protocol):
    """The contract between the mission loop and the modules' transport."""

    mode: str
    """``in-process`` or ``processes`` (recorded in metrics.json)."""

    @property
    def cfg(self) -> MissionConfig:
        """The mission's configuration as it stands: the one the loop reads at each step
        boundary (a ground command changes the process set's there; in process it is the
        launch configuration throughout)."""
        ...

    def start(self) -> None:
        """Bring every module up; return when all are ready for step 0."""
        ...

    def ask(self, topic: str) -> Any:
        """The value of a queryable (the mission asks for ``truth_surface``)."""
        ...

    def tick(self, status: MissionStatus) -> None:
        """Publish the clock: a ``running`` status starts step ``status.step``."""
        ...

    def receive(self, name: str, step: int) -> Any:
        """The mission's input ``name`` (see ``MODULES["mission"].inputs``) of ``step``,
        waiting for it if it has not come yet."""
        ...

    def poll(self, name: str, step: int) -> Any | None:
        """The mission's input ``name`` of ``step`` if it has come, else None, without
        waiting: for diagnostics a module may not publish (a planner of the user's own need
        not publish ``rejected``), read after an output its module publishes later."""
        ...

    def timings(self) -> list[StepTiming]:
        """Every stage timing the modules reported, one per (stage, step)."""
        ...

    def dropped(self) -> int:
        """Malformed messages dropped, by the modules and the mission."""
        ...

    def restarts(self) -> list[dict[str, Any]]:
        """Modules that died and were restarted."""
        ...

    def finish(self, final: MissionStatus, failed: bool) -> None:
        """Publish the final status, stop every module, release everything. Raises
        :class:`MissionFailed` when a module did not exit cleanly (unless ``failed``)."""
        ...


#: Topics whose messages are large (clouds, images): handed to the taps unencoded, to be
#: encoded on a tap's own thread. Their arrays are made read-only first: every module makes
#: them afresh each step, and none may change one it sent or received (a test run of every
#: in-process mission, recorded by default, holds them to it).
_DEFERRED = frozenset({"depth", "surface", "predicted", "planner_map"})


def _payload(topic: str, value: Any):
    """What the taps get for a value of ``topic``: its CDR bytes, or for a large message a
    :class:`rovergate.taps.Deferred` encoding of it."""
    if topic not in _DEFERRED:
        return encode(topic, value)
    from rovergate.taps import Deferred
    arrays = [a for a in (value[1] if isinstance(value, tuple) else value.points,)
              if isinstance(a, np.ndarray)]
    if isinstance(value, CloudUpdate):  # an incremental map's (rovergate.streams)
        arrays = [value.points, value.put_at, value.copy_to, value.copy_from, value.copy_count,
                  value.patch_at, *([] if value.patches is None else [value.patches])]
    for a in arrays:
        a.flags.writeable = False
    return Deferred(lambda: encode(topic, value), sum(a.nbytes for a in arrays))


class InProcessTransport:
    """Every module's logic in this process, driven by the graph: a tick is delivered to the
    modules that read it, and every module whose inputs of its next step are complete runs,
    its outputs delivered in turn, until none can."""

    mode = "in-process"

    def __init__(self, cfg: MissionConfig, taps: Taps | None = None) -> None:
        """``taps`` (the flight recorder, the live view) get every message a module
        publishes, encoded as the process set would send it."""
        self.cfg = cfg
        self.taps = taps
        self.logic: dict[str, ModuleLogic] = {}
        self._buffers: dict[str, dict[str, dict[int, Any]]] = {
            m: {n: {} for n in MODULES[m].inputs} for m in (*LAUNCHED, "mission")}
        self._next: dict[str, int] = dict.fromkeys(LAUNCHED, 0)
        self._timings: list[StepTiming] = []
        # The taps get the incremental maps as the process set's modules send them.
        self._encoders = {t: StreamEncoder(t, cfg.session.keyframe_every) for t in INCREMENTAL}

    def start(self) -> None:
        from mission.runtime.modules import make_logic
        try:
            # Modules that serve queryables first: the others may ask them while being built
            # (the gate asks the simulator for the reference occupancy).
            for name in sorted(LAUNCHED, key=lambda m: not MODULES[m].serves):
                self.logic[name] = make_logic(name, self.cfg, self.ask)
        except BaseException:
            self._close()
            raise

    def ask(self, topic: str) -> Any:
        return stamped(topic, self.logic[producer(topic)].serve(topic))[1]

    def tick(self, status: MissionStatus) -> None:
        self._deliver("status", status)
        progress = True
        while progress:
            progress = False
            for name, logic in self.logic.items():
                step, spec = self._next[name], logic.spec
                buffers = self._buffers[name]
                if step > spec.last_step(self.cfg.steps) or spec.missing(step, buffers):
                    continue
                out = logic.handle(step, spec.take(step, buffers))
                timings = [StepTiming(step, stage, s, 0) for stage, s in out.stages.items()]
                self._timings += timings
                for topic, value in out.messages:
                    self._deliver(topic, value)
                if self.taps:
                    for timing in timings:
                        self.taps.put("timing", encode("timing", timing))
                self._next[name] = step + 1
                progress = True

    def _deliver(self, topic: str, value: Any) -> None:
        if self.taps:
            sent = self._encoders[topic].encode(value) if topic in self._encoders else value
            self.taps.put(topic, _payload(topic, sent))
        step, value = stamped(topic, value)
        for module, name, _ in consumers(topic):
            self._buffers[module][name][step] = value

    def poll(self, name: str, step: int) -> Any | None:
        return self._buffers["mission"][name].pop(step, None)

    def receive(self, name: str, step: int) -> Any:
        try:
            return self._buffers["mission"][name].pop(step)
        except KeyError:
            raise MissionFailed(f"no {name} of step {step}: the modules produced none") from None

    def timings(self) -> list[StepTiming]:
        return list(self._timings)

    def dropped(self) -> int:
        return 0

    def restarts(self) -> list[dict[str, Any]]:
        return []

    def finish(self, final: MissionStatus, failed: bool) -> None:
        if self.taps:  # the process set's clock publishes the final status too
            self.taps.put("status", encode("status", final))
        self._close()

    def _close(self) -> None:
        while self.logic:
            self.logic.popitem()[1].close()
