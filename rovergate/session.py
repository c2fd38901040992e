"""Opening a Zenoh session from the session flags (:class:`rovergate.config.SessionConfig`).

This and :mod:`rovergate.node` are the shared package's only Zenoh imports: the configuration
and every module's logic load without it."""

from __future__ import annotations

import json
import re
import socket
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import zenoh

from rovergate.config import SessionConfig
from rovergate.errors import ConfigError


@dataclass(frozen=True)
class TlsFiles:
    """One party's mutual-TLS credentials (``rovergate credentials`` writes them): the
    mission's certificate authority, and this party's certificate and private key (PEM)."""

    ca: Path
    cert: Path
    key: Path

    def check(self) -> None:
        """ConfigError naming the first file that is missing or unreadable."""
        for path in (self.ca, self.cert, self.key):
            try:
                with open(path, "rb") as f:
                    if b"-----BEGIN" not in f.read(4096):
                        raise ConfigError(f"{path} is not a PEM file; create the credentials "
                                          "with `rovergate credentials --out DIR`")
            except OSError as exc:
                raise ConfigError(f"cannot read the credential {path} ({exc.strerror}); "
                                  "create them with `rovergate credentials --out DIR`") from None


#: How long a peer with TLS credentials tries to connect before it gives up (a refused
#: certificate shows as this timeout).
TLS_CONNECT_TIMEOUT_S = 15.0


def zenoh_config(cfg: SessionConfig, access_control: dict[str, Any] | None = None,
                 tls: TlsFiles | None = None,
                 connect_timeout_s: float = TLS_CONNECT_TIMEOUT_S) -> zenoh.Config:
    """The zenoh.Config of a :class:`SessionConfig`, with an ``access_control`` section
    (:mod:`rovergate.access`) and mutual-TLS credentials when given (a TLS peer gives up
    connecting after ``connect_timeout_s``)."""
    conf = zenoh.Config()
    conf.insert_json5("mode", json.dumps(cfg.mode))
    conf.insert_json5("connect/endpoints", json.dumps(list(cfg.connect)))
    conf.insert_json5("listen/endpoints", json.dumps(list(cfg.listen)))
    conf.insert_json5("scouting/multicast/enabled", json.dumps(cfg.multicast_scouting))
    if access_control is not None:
        conf.insert_json5("access_control", json.dumps(access_control))
    if tls is not None:
        tls.check()
        link = {"root_ca_certificate": str(tls.ca), "enable_mtls": True}
        if cfg.listen:
            link |= {"listen_certificate": str(tls.cert), "listen_private_key": str(tls.key)}
        if cfg.connect:
            link |= {"connect_certificate": str(tls.cert), "connect_private_key": str(tls.key),
                     "verify_name_on_connect": True}
        conf.insert_json5("transport/link/tls", json.dumps(link))
    if tls is not None and cfg.connect:
        # A peer that gets no TLS link fails after the timeout, instead of retrying in the
        # background as if the link were slow (a refused certificate shows as that timeout).
        conf.insert_json5("connect/timeout_ms", str(max(1, int(connect_timeout_s * 1000))))
        conf.insert_json5("connect/exit_on_failure", "true")
    return conf


def zenoh_reason(exc: BaseException) -> str:
    """Zenoh's error text without the Rust source location it ends with (``at
    .../orchestrator.rs:388.``), which tells a user nothing."""
    return _RUST_LOCATION.sub("", str(exc)).strip().rstrip(".!") or type(exc).__name__


_RUST_LOCATION = re.compile(r"\s*at\s+\S+\.rs:\d+(:\d+)?\.?")


def open_session(cfg: SessionConfig, access_control: dict[str, Any] | None = None,
                 tls: TlsFiles | None = None,
                 connect_timeout_s: float = TLS_CONNECT_TIMEOUT_S) -> zenoh.Session:
    """Open a Zenoh session; a bad endpoint gives one line saying which and how to fix it."""
    try:
        return zenoh.open(zenoh_config(cfg, access_control, tls, connect_timeout_s))
    except Exception as exc:
        raise ConfigError(
            f"could not open a Zenoh session (mode={cfg.mode}, listen={list(cfg.listen)}, "
            f"connect={list(cfg.connect)}): {zenoh_reason(exc)}. Check the endpoints: they "
            "look like tcp/127.0.0.1:7447, a listen port must be free, and a tls/ endpoint needs "
            "credentials from the same CA as its peer's (a refused certificate shows as a "
            "timeout).") from None


def free_loopback_port() -> int:
    """A TCP port on 127.0.0.1 that nothing listens on right now."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])
