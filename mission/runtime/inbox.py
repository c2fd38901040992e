"""The mission's inbox: the messages its loop awaits, by topic and step."""

from __future__ import annotations

import threading
from typing import Any


class Inbox:
    """Step-indexed messages put by the transport's callbacks and popped by the loop.

    ``cv`` is the condition every wait of the Zenoh transport sleeps on; whoever changes what
    a wait looks at (a message, a liveliness token) notifies it.
    """

    def __init__(self, topics: set[str] | frozenset[str]) -> None:
        self.cv = threading.Condition()
        self._items: dict[str, dict[int, Any]] = {t: {} for t in topics}
        self.last_seen: dict[str, int] = {}
        """The latest step seen on each topic (a restarted module resumes at its own)."""

    def put(self, topic: str, step: int, value: Any) -> None:
        """Store a message; the caller holds ``cv``."""
        self.last_seen[topic] = max(step, self.last_seen.get(topic, -1))
        if topic in self._items:
            self._items[topic][step] = value
        self.cv.notify_all()

    def has(self, topic: str, step: int) -> bool:
        return step in self._items[topic]

    def pop(self, topic: str, step: int) -> Any:
        return self._items[topic].pop(step)
