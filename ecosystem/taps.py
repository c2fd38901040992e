"""Taps: what receives a copy of every message the mission's modules publish, as CDR bytes.

A tap is anything with ``put(topic, payload, time_ns)`` and ``close()``. The mission feeds
them from whichever transport carries the messages: the process set's mission manager from
its Zenoh subscriptions (the bytes as they travelled), the in-process loop from each value it
routes (encoded as the process set would send it), and ``rovergate replay`` from a bag. A tap
must not block: it is called on the transport's own thread.
"""

from __future__ import annotations

import logging
import threading
import time
from typing import Protocol

from rovergate.graph import TOPICS

log = logging.getLogger("rovergate.taps")


def tapped_topics() -> tuple[str, ...]:
    """The topics a tap receives: every published topic of the rover's network (the ground
    link's telemetry is the ground station's record; queryables are not published)."""
    return tuple(name for name, t in TOPICS.items() if t.network == "rover" and t.kind == "topic")


class Tap(Protocol):
    def put(self, topic: str, payload: bytes, time_ns: int) -> None:
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

    def put(self, topic: str, payload: bytes, time_ns: int | None = None) -> None:
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
