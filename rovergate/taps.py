"""Taps: what receives a copy of every message the mission's modules publish, as CDR bytes.

A tap is anything with ``put(topic, payload, time_ns)`` and ``close()``. The mission feeds
them from whichever transport carries the messages: the process set's mission manager from
its Zenoh subscriptions (the bytes as they travelled), the in-process loop from each value it
routes (encoded as the process set would send it), and ``rovergate replay`` from a bag. A tap
must not block: it is called on the transport's own thread.

A payload is ``bytes``, or a :class:`Deferred` message that is encoded when a tap first needs
its bytes (``bytes(payload)``): the in-process loop hands its large messages over that way,
so that a tap with a thread of its own encodes them there, not on the loop's thread.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from typing import Protocol

from rovergate.graph import TOPICS

log = logging.getLogger("rovergate.taps")


def tapped_topics() -> tuple[str, ...]:
    """The topics a tap receives: every published topic of the rover's network (the ground
    link's telemetry is the ground station's record; queryables are not published)."""
    return tuple(name for name, t in TOPICS.items() if t.network == "rover" and t.kind == "topic")


class Deferred:
    """A message encoded once, when a tap first asks for its bytes (from any thread).
    ``len()`` is an estimate of its size until then (its arrays' bytes)."""

    __slots__ = ("_encode", "_data", "_lock", "size_hint")

    def __init__(self, encode: Callable[[], bytes], size_hint: int) -> None:
        self._encode: Callable[[], bytes] | None = encode
        self._data: bytes | None = None
        self._lock = threading.Lock()
        self.size_hint = size_hint

    def __bytes__(self) -> bytes:
        with self._lock:
            if self._data is None and self._encode is not None:
                self._data = self._encode()
                self._encode = None  # the value it held may go
            return self._data if self._data is not None else b""

    def __len__(self) -> int:
        return len(self._data) if self._data is not None else self.size_hint


Payload = bytes | Deferred


class Tap(Protocol):
    def put(self, topic: str, payload: Payload, time_ns: int) -> None:
        """One message of ``topic`` (a name of :data:`rovergate.graph.TOPICS`), received at
        ``time_ns`` (nanoseconds since the epoch)."""
        ...

    def close(self) -> None:
        """Finish: flush what is pending and release everything."""
        ...


class Taps:
    """Several taps as one; a tap that raises is closed and dropped (logged once), so that a
    full disk or a viewer's fault never stops the mission."""

    def __init__(self, taps: list[Tap]) -> None:
        self.taps = list(taps)
        self._lock = threading.Lock()

    def __bool__(self) -> bool:
        return bool(self.taps)

    def put(self, topic: str, payload: Payload, time_ns: int | None = None) -> None:
        now = time.time_ns() if time_ns is None else time_ns
        for tap in list(self.taps):
            try:
                tap.put(topic, payload, now)
            except Exception as exc:
                with self._lock:  # the transport calls from several threads
                    if tap not in self.taps:
                        continue
                    self.taps.remove(tap)
                log.error("%s failed and is stopped: %s", type(tap).__name__, exc)
                self._close(tap)

    def close(self) -> None:
        while self.taps:
            self._close(self.taps.pop(0))

    @staticmethod
    def _close(tap: Tap) -> None:
        try:
            tap.close()
        except Exception as exc:
            log.error("%s did not close cleanly: %s", type(tap).__name__, exc)
