"""Opening a Zenoh session from the session flags (:class:`rovergate.config.SessionConfig`).

This and :mod:`rovergate.node` are the shared package's only Zenoh imports: the configuration
and every module's logic load without it."""

from __future__ import annotations

import json
import socket

import zenoh

from rovergate.config import SessionConfig
from rovergate.errors import ConfigError


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
        raise ConfigError(
            f"could not open a Zenoh session (mode={cfg.mode}, listen={list(cfg.listen)}, "
            f"connect={list(cfg.connect)}): {exc}. Check the endpoints: they look like "
            "tcp/127.0.0.1:7447, and a listen port must be free.") from None


def free_loopback_port() -> int:
    """A TCP port on 127.0.0.1 that nothing listens on right now."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])
