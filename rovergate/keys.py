"""Key expressions: the topics of :mod:`rovergate.graph` resolved under a namespace.

All keys live under a namespace (default ``rover``; the ground network's under ``ground``). The
Zenoh encoding of every sample is ``application/cdr`` with the ROS 2 type name as its schema,
so a subscriber can check what it receives.
"""

from __future__ import annotations

from dataclasses import dataclass

from rovergate.graph import TOPICS


@dataclass(frozen=True)
class Keys:
    """Resolves topics and liveliness tokens under one namespace."""

    namespace: str = "rover"

    def key(self, topic: str) -> str:
        """Full key expression of a topic name from :data:`rovergate.graph.TOPICS`."""
        return f"{self.namespace}/{TOPICS[topic].suffix}"

    def alive(self, module: str) -> str:
        """Liveliness token a module declares once it is ready."""
        return f"{self.namespace}/alive/{module}"

    @property
    def alive_all(self) -> str:
        return f"{self.namespace}/alive/*"

    def journal(self, topic: str) -> str:
        """Queryable of the mission's journal of a topic: the samples of past steps, which a
        restarted module replays (parameters ``from`` and ``to``, steps inclusive)."""
        return f"{self.namespace}/mission/journal/{TOPICS[topic].suffix}"
