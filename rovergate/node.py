"""The node runtime: a thin wrapper that puts a module's logic on the Zenoh network.

A :class:`ModuleNode` takes a module's declaration from :mod:`rovergate.graph` and its logic
(:class:`rovergate.module.ModuleLogic`), and owns the session, the publishers and
subscriptions, the queryables it serves, the liveliness token that says the module is ready,
and the lockstep: the logic handles step t once every input for step t has arrived (an input
with ``lag=1`` is the message of step t-1, absent at t=0). Module logic never imports Zenoh;
only this module, :mod:`rovergate.session` and the mission's Zenoh transport do.

A message that does not decode, or has the wrong encoding, type or shape, is logged with its
key and the reason, counted, and dropped; the process runs on.
"""

from __future__ import annotations

import contextlib
import functools
import logging
import queue
import resource
import threading
import time
from collections.abc import Callable
from typing import Any

import zenoh

from rovergate.config import SessionConfig
from rovergate.errors import TransportError
from rovergate.graph import TOPICS, Module
from rovergate.keys import Keys
from rovergate.logs import log_drop
from rovergate.messages import MessageError, decode, encode, prepare
from rovergate.module import STOP, ModuleLogic, StepOutput
from rovergate.session import open_session
from rovergate.streams import INCREMENTAL, StreamDecoder, StreamEncoder
from rovergate.types import StepTiming

_MISSION_LOST = "__mission_lost__"


def cdr_encoding(topic: str) -> zenoh.Encoding:
    """``application/cdr`` with the topic's ROS 2 type name as schema."""
    return zenoh.Encoding.APPLICATION_CDR.with_schema(TOPICS[topic].msgtype)


def stamp_of(topic: str, sample: zenoh.Sample) -> int:
    """The planning step of a sample of ``topic``, read from its header without decoding the
    rest (``header.stamp.sec``, the first field of every rovergate message, right after the
    4-byte CDR encapsulation). Raises MessageError when the sample's encoding is not the
    topic's or the bytes do not start as little-endian CDR; the rest of the message is not
    checked (the module that replays it decodes it, and drops it if it is malformed)."""
    want = str(cdr_encoding(topic))
    if str(sample.encoding) != want:
        raise MessageError(f"encoding is {str(sample.encoding)!r}, expected {want!r}")
    head = sample.payload.to_bytes()[:8]
    if len(head) < 8 or head[:2] != b"\x00\x01":
        raise MessageError("not a little-endian CDR message")
    return int.from_bytes(head[4:8], "little", signed=True)


def check_and_decode(topic: str, sample: zenoh.Sample) -> tuple[int, Any]:
    """Decode a sample of ``topic``, checking its encoding first. Raises MessageError."""
    want = str(cdr_encoding(topic))
    got = str(sample.encoding)
    if got != want:
        raise MessageError(f"encoding is {got!r}, expected {want!r}")
    return decode(topic, sample.payload.to_bytes())


class Drops:
    """A thread-safe count of the messages a process dropped, each logged as
    :func:`rovergate.logs.log_drop` does (the first ones, then one in many)."""

    def __init__(self, log: logging.Logger, what: str = "message") -> None:
        self.log = log
        self.what = what
        self.count = 0
        self._lock = threading.Lock()

    def drop(self, where: str, why: object) -> None:
        with self._lock:
            self.count += 1
            count = self.count
        log_drop(self.log, count, self.what, where, why)


def decoding(topic: str, key: str, drops: Drops,
             handle: Callable[[int, Any, zenoh.Sample], None]) -> Callable[[zenoh.Sample], None]:
    """The subscriber callback of ``topic`` (on ``key``): each sample decoded (its encoding
    checked first) and handed to ``handle(step, value, sample)``, or, when it does not decode,
    counted and logged in ``drops`` and nothing else: a bad message loses no good one."""
    def on_sample(sample: zenoh.Sample) -> None:
        try:
            step, value = check_and_decode(topic, sample)
        except MessageError as exc:
            drops.drop(key, exc)
            return
        handle(step, value, sample)
    return on_sample


def ask_until_answered(session: zenoh.Session, key: str, topic: str, who: str,
                       timeout_s: float, log: logging.Logger,
                       before_each: Callable[[], None] | None = None) -> Any:
    """The value the queryable on ``key`` serves (``topic``'s message), asked as ``who``
    again and again until an answer decodes (a queryable just declared may not be routed
    yet); an answer that does not decode is logged and dropped. ``before_each`` runs before
    each try (the mission checks its processes there). Raises :class:`TimeoutError` when no
    answer came within ``timeout_s``."""
    deadline = time.monotonic() + timeout_s
    while (left := deadline - time.monotonic()) > 0:
        if before_each is not None:
            before_each()
        for reply in session.get(key, timeout=min(10.0, max(left, 0.1)), attachment=who):
            if reply.ok is not None:
                try:
                    return check_and_decode(topic, reply.ok)[1]
                except MessageError as exc:
                    log.warning("dropped a reply on %s: %s", key, exc)
        time.sleep(0.2)  # no answer yet: ask again after a pause, not in a busy loop
    raise TimeoutError(key)


class ModuleNode:
    """Session, subscriptions, liveliness and lockstep for one module process."""

    def __init__(self, spec: Module, session_cfg: SessionConfig, log: logging.Logger) -> None:
        self.spec = spec
        self.name = spec.name
        self.session_cfg = session_cfg
        self.log = log
        self.keys = Keys(session_cfg.namespace)
        self.inputs = dict(spec.inputs)
        outputs = list(spec.outputs)
        self.drops = Drops(log)
        self._queue: queue.Queue[tuple[str, int, Any]] = queue.Queue()
        self._buffers: dict[str, dict[int, Any]] = {n: {} for n in self.inputs}
        self._lock = threading.Lock()
        self._token: zenoh.LivelinessToken | None = None
        self.session = open_session(session_cfg)
        prepare({*self.spec.outputs, *self.spec.serves, *self.spec.asks, "timing", "status",
                 *(i.topic for i in self.inputs.values())})
        # BLOCK, not zenoh's default DROP: in lockstep every message is awaited, and DROP
        # discards a sample when a link's queue is full (a subscriber busy for a moment), which
        # lost the mission's copy of a step's prediction while the gate got its own.
        self._publishers = {
            t: self.session.declare_publisher(self.keys.key(t), encoding=cdr_encoding(t),
                                              congestion_control=zenoh.CongestionControl.BLOCK)
            for t in [*outputs, "timing"]}
        # The status topic is always watched: it carries the end of the mission.
        watched = {i.topic for i in self.inputs.values()} | {"status"}
        self._subscribers = [
            self.session.declare_subscriber(self.keys.key(t), self._callback(t)) for t in watched]
        self._mission_seen = False
        self._watchdog = self.session.liveliness().declare_subscriber(
            self.keys.alive("mission"), self._on_mission_liveliness, history=True)
        self._queryables: list[zenoh.Queryable[None]] = []
        self._first_step = 0
        # The incremental maps (rovergate.streams): a fresh encoder's first message is a
        # keyframe, so a restarted module's readers take it up at once.
        self._encoders = {t: StreamEncoder(t, session_cfg.keyframe_every)
                          for t in outputs if t in INCREMENTAL}
        self._decoders = {t: StreamDecoder(t) for t in watched if t in INCREMENTAL}

    # --- receiving ------------------------------------------------------------------------

    @property
    def dropped(self) -> int:
        """Messages this node dropped (they did not decode)."""
        return self.drops.count

    def _callback(self, topic: str) -> Callable[[zenoh.Sample], None]:
        return decoding(topic, self.keys.key(topic), self.drops,
                        lambda step, value, _: self._queue.put((topic, step, value)))

    def _on_mission_liveliness(self, sample: zenoh.Sample) -> None:
        if sample.kind == zenoh.SampleKind.PUT:
            self._mission_seen = True
        elif self._mission_seen:
            self._queue.put((_MISSION_LOST, -1, None))

    # --- sending --------------------------------------------------------------------------

    def publish(self, topic: str, value: Any) -> None:
        """Encode ``value`` as the topic's ROS 2 type and put it."""
        if topic in self._encoders:
            value = self._encoders[topic].encode(value)
        self._publishers[topic].put(encode(topic, value))

    def serve(self, topic: str, make_value: Callable[[], Any]) -> None:
        """Answer queries on ``topic`` with the encoded value of ``make_value()``."""
        key = self.keys.key(topic)
        encoding = cdr_encoding(topic)

        def on_query(query: zenoh.Query) -> None:
            # Every answer is logged with who asked (the requester names itself in the
            # attachment): the record that ground truth reaches only those allowed it.
            who = query.attachment.to_string() if query.attachment is not None else "unnamed"
            self.log.info("served %s to %s", key, who)
            query.reply(key, encode(topic, make_value()), encoding=encoding)
        self._queryables.append(self.session.declare_queryable(key, on_query))

    def query(self, topic: str, timeout_s: float) -> Any:
        """Fetch the value a queryable serves on ``topic``, retrying until ``timeout_s``."""
        key = self.keys.key(topic)
        try:
            return ask_until_answered(self.session, key, topic, self.name, timeout_s, self.log)
        except TimeoutError:
            raise TransportError(f"{self.name}: no answer on {key} within {timeout_s:.0f} s; "
                                 "is the simulator running in this namespace?") from None

    def wait_for_peers(self, timeout_s: float = 60.0) -> None:
        """With ``wait_for_peers`` set, wait until that many peers are linked, so that
        messages published right after the mission starts reach their subscribers."""
        want = self.session_cfg.wait_for_peers
        deadline = time.monotonic() + timeout_s
        while want and len(list(self.session.info.peers_zid())) < want:
            if time.monotonic() > deadline:
                have = len(list(self.session.info.peers_zid()))
                raise TransportError(f"{self.name}: only {have} of {want} Zenoh peers linked "
                                     f"after {timeout_s:.0f} s; check the --connect/--listen "
                                     "endpoints")
            time.sleep(0.01)

    def ready(self, timeout_s: float = 60.0) -> None:
        """Declare this module's liveliness token: everything is subscribed and loaded."""
        self.wait_for_peers(timeout_s)
        self._token = self.session.liveliness().declare_token(self.keys.alive(self.name))
        self.log.info("ready: liveliness token %s declared", self.keys.alive(self.name))

    # --- recovery ---------------------------------------------------------------------------

    def fetch_journal(self, topic: str, first: int, last: int, timeout_s: float = 30.0
                      ) -> dict[int, Any]:
        """The samples of ``topic`` for steps ``first..last`` that the mission journalled."""
        out: dict[int, Any] = {}
        if last < first:
            return out
        selector = f"{self.keys.journal(topic)}?from={first};to={last}"
        # One reply per step, all on the same key: zenoh's default consolidation would keep
        # only the latest of them.
        for reply in self.session.get(selector, timeout=timeout_s, attachment=self.name,
                                      consolidation=zenoh.ConsolidationMode.NONE):
            if reply.ok is None:
                continue
            try:
                step, value = check_and_decode(topic, reply.ok)
            except MessageError as exc:
                self.log.warning("dropped a journal reply on %s: %s", selector, exc)
                continue
            out[step] = value
        return out

    def resume(self, step: int, logic: ModuleLogic, timeout_s: float = 60.0) -> None:
        """Rebuild this module's state after a restart, then take up the lockstep at ``step``.

        ``logic.restore(s, inputs)`` is called for every step s < ``step`` with that step's
        ``replay`` inputs (:mod:`rovergate.graph`) from the mission's journal (a module is a
        deterministic function of its inputs, so this rebuilds exactly the state it had);
        then the inputs of ``step`` on, published while the module was down, are taken from
        the journal.
        """
        restore_inputs = {n: self.spec.inputs[n] for n in self.spec.replay}
        # The mission journals every tick: an answer proves that the journal is reachable
        # (right after a session opens, a query may not be routed yet).
        deadline = time.monotonic() + timeout_s
        while not self.fetch_journal("status", 0, step, timeout_s=5.0):
            if time.monotonic() > deadline or STOP.is_set():
                raise TransportError(f"{self.name}: the mission's journal "
                                     f"({self.keys.journal('status')}) did not answer within "
                                     f"{timeout_s:.0f} s; cannot resume at step {step}")
            time.sleep(0.1)
        t0 = time.perf_counter()
        if restore_inputs:
            history = {n: self.fetch_journal(i.topic, 0, step - 1 - i.lag)
                       for n, i in restore_inputs.items()}
            for s in range(step):
                missing = [n for n, i in restore_inputs.items()
                           if s - i.lag >= 0 and s - i.lag not in history[n]]
                if missing:
                    raise TransportError(f"{self.name}: the mission's journal lacks "
                                         f"{', '.join(missing)} of step {s}; cannot resume")
                logic.restore(s, {n: history[n].get(s - i.lag)
                                  for n, i in restore_inputs.items()})
        # Inputs of this step and any later one already sent (the module redoes the last
        # step it finished, so the next step's inputs may be out too).
        for name, inp in self.inputs.items():
            first = max(0, step - inp.lag)
            if inp.topic in self._decoders and first > 0:
                # An incremental map: also the step before, whole (the journal's first reply
                # is), the base of the next update, which may not be out yet.
                journalled = self.fetch_journal(inp.topic, first - 1, 2**31 - 1)
                if first - 1 in journalled:
                    try:
                        self._decoders[inp.topic].apply(journalled.pop(first - 1))
                    except MessageError as exc:
                        self.log.warning("journalled %s of step %d: %s", inp.topic,
                                         first - 1, exc)
            else:
                journalled = self.fetch_journal(inp.topic, first, 2**31 - 1)
            self._buffers[name].update(journalled)
        self._first_step = step
        self.log.debug("journalled inputs: %s", {n: sorted(b) for n, b in self._buffers.items()})
        self.log.info("resumed at step %d (state rebuilt from %d journalled steps in %.2f s)",
                      step, step, time.perf_counter() - t0)

    # --- the lockstep ---------------------------------------------------------------------

    def _missing(self, step: int) -> list[str]:
        return self.spec.missing(step, self._buffers)

    def _handle_complete(self, logic: ModuleLogic, step: int, last_step: int | None) -> int:
        """Handle every step, from ``step`` on, whose inputs are all in; returns the first step
        still waiting."""
        while not self._missing(step) and (last_step is None or step <= last_step):
            inputs = self.spec.take(step, self._buffers)
            for name, value in inputs.items():
                topic = self.inputs[name].topic
                if topic in self._decoders and value is not None:
                    try:
                        inputs[name] = self._decoders[topic].apply(value)
                    except MessageError as exc:  # a lost message: the lockstep cannot go on
                        raise TransportError(f"{self.name}: {self.keys.key(topic)}: {exc}; "
                                             "restart the module to take it up again from "
                                             "the journal") from None
            out: StepOutput = logic.handle(step, inputs)
            for topic, value in out.messages:
                self.publish(topic, value)
            for stage, seconds in out.stages.items():
                self.publish("timing", StepTiming(step, stage, seconds, self.dropped))
            step += 1
        return step

    def spin(self, logic: ModuleLogic, idle_timeout_s: float, last_step: int | None = None
             ) -> str:
        """Handle step 0, 1, ... as each step's inputs complete, publishing what the logic
        produces and its stage timings.

        Returns why it stopped: ``done`` or ``aborted`` (the mission said so), ``mission-lost``
        (the mission's liveliness token vanished) or ``idle-timeout``.
        """
        # A resumed module may hold a complete step already (from the journal).
        step = self._handle_complete(logic, self._first_step, last_step)
        while True:
            deadline = time.monotonic() + idle_timeout_s
            item = None
            while item is None and not STOP.is_set() and time.monotonic() < deadline:
                with contextlib.suppress(queue.Empty):
                    item = self._queue.get(timeout=0.1)
            if STOP.is_set():
                self.log.info("interrupted; stopping")
                return "interrupted"
            if item is None:
                awaited = ", ".join(f"{self.keys.key(self.inputs[n].topic)} step "
                                    f"{step - self.inputs[n].lag}" for n in self._missing(step))
                self.log.error("no input for %.0f s; awaited %s", idle_timeout_s, awaited)
                return "idle-timeout"
            topic, msg_step, value = item
            if topic == _MISSION_LOST:
                self.log.error("the mission's liveliness token vanished; stopping")
                return "mission-lost"
            if topic == "status" and value.state in ("done", "aborted"):
                self.log.info("mission %s at step %d; stopping", value.state, value.step)
                return str(value.state)
            if topic == "status" and value.state == "paused":
                continue  # the mission holds the clock: a keep-alive, not a tick
            for name, inp in self.inputs.items():
                if inp.topic == topic and msg_step >= step - inp.lag:
                    if topic in self._decoders:  # a journal keyframe stays (the base)
                        self._buffers[name].setdefault(msg_step, value)
                    else:
                        self._buffers[name][msg_step] = value
            step = self._handle_complete(logic, step, last_step)

    def run(self, logic: ModuleLogic, idle_timeout_s: float, last_step: int | None = None,
            resume_step: int | None = None) -> int:
        """Serve the module's queryables, declare readiness, spin until the mission ends,
        close; returns the exit code (0 when the mission said done or aborted).

        ``resume_step`` (a restarted module, 0 included: the tick of step 0 may be out
        already): first rebuild the state from the journal (:meth:`resume`)."""
        try:
            for topic in self.spec.serves:
                self.serve(topic, functools.partial(logic.serve, topic))
            if resume_step is not None:
                self.wait_for_peers()
                self.resume(resume_step, logic)
            self.ready()
            reason = self.spin(logic, idle_timeout_s, last_step)
        finally:
            self.close()
        return 0 if reason in ("done", "aborted", "interrupted") else 1

    def close(self) -> None:
        """Undeclare everything and close the session; logs the process's peak memory."""
        peak_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024  # KiB on Linux
        self.log.info("peak resident memory %.0f MB", peak_mb)
        if self._token is not None:
            self._token.undeclare()
        for q in self._queryables:
            q.undeclare()
        for s in self._subscribers:
            s.undeclare()
        self._watchdog.undeclare()
        self.session.close()
