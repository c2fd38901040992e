"""The mission clock: the ticks on ``<ns>/mission/status`` that start every step."""

from __future__ import annotations

import threading
from typing import TYPE_CHECKING

import zenoh

from mission.runtime.journal import Journal
from rovergate.keys import Keys
from rovergate.messages import encode
from rovergate.node import cdr_encoding
from rovergate.types import MissionStatus

if TYPE_CHECKING:
    from rovergate.taps import Taps


class MissionClock:
    """Publishes the mission's status: a ``running`` tick starts a step (and is journalled,
    as a restarted simulator replays the ticks), ``paused`` keeps the modules waiting,
    ``done`` or ``aborted`` ends them."""

    def __init__(self, session: zenoh.Session, keys: Keys, journal: Journal,
                 lock: threading.Condition | threading.Lock, taps: Taps | None = None
                 ) -> None:
        """``taps`` (the flight recorder, the live view) get every status it publishes."""
        self.journal = journal
        self.taps = taps
        self._lock = lock
        # BLOCK: every tick is awaited; zenoh's default DROP may discard one under load.
        self._publisher = session.declare_publisher(
            keys.key("status"), encoding=cdr_encoding("status"),
            congestion_control=zenoh.CongestionControl.BLOCK)

    def publish(self, status: MissionStatus) -> None:
        payload = encode("status", status)
        if status.state == "running":
            with self._lock:
                self.journal.add("status", status.step, payload)
        self._publisher.put(payload)
        if self.taps:
            self.taps.put("status", payload)

    def close(self) -> None:
        self._publisher.undeclare()
