"""Zenoh session configuration shared by every program (the session flags)."""

from __future__ import annotations

import json
import socket
from dataclasses import dataclass
from typing import Literal

import zenoh


@dataclass
class SessionConfig:
    """How a process joins the Zenoh network."""

    mode: Literal["peer", "client", "router"] = "peer"
    """Zenoh mode of this process."""
    connect: tuple[str, ...] = ()
    """Endpoints to connect to, e.g. tcp/127.0.0.1:7447."""
    listen: tuple[str, ...] = ()
    """Endpoints to listen on, e.g. tcp/0.0.0.0:7447 to let other machines connect."""
    namespace: str = "rover"
    """Prefix of every key expression, so that several rovers can share one network."""
    multicast_scouting: bool = False
    """Discover peers by UDP multicast. Off by default: endpoints are explicit."""
    wait_for_peers: int = 0
    """Before declaring itself ready, wait until this many peers are linked (`rovergate run`
    sets it so that the first messages of a mission reach every module)."""


def zenoh_config(cfg: SessionConfig) -> zenoh.Config:
    """The zenoh.Config of a :class:`SessionConfig`."""
    conf = zenoh.Config()
    conf.insert_json5("mode", json.dumps(cfg.mode))
    conf.insert_json5("connect/endpoints", json.dumps(list(cfg.connect)))
    conf.insert_json5("listen/endpoints", json.dumps(list(cfg.listen)))
    conf.insert_json5("scouting/multicast/enabled", json.dumps(cfg.multicast_scouting))
    return conf


def open_session(cfg: SessionConfig) -> zenoh.Session:
    """Open a Zenoh session; a bad endpoint gives one line saying which and how to fix it."""
    try:
        return zenoh.open(zenoh_config(cfg))
    except Exception as exc:
        raise SystemExit(
            f"error: could not open a Zenoh session (mode={cfg.mode}, listen={list(cfg.listen)}, "
            f"connect={list(cfg.connect)}): {exc}. Check the endpoints: they look like "
            "tcp/127.0.0.1:7447, and a listen port must be free.") from None


def free_loopback_port() -> int:
    """A TCP port on 127.0.0.1 that nothing listens on right now."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])
