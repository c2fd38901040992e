"""The operator's console: a page in a browser, served by the ground station
(``rovergate ground --web``, or a mission file's ``[ground] web = true``).

It shows what the ground knows, from what came down the link only (the station's
:class:`mission.link.store.GroundStore`): the last downlinked step and its age in mission
time, the step the rover is predicted to be at, its state; the contact plan as a timeline with
the light time, the onboard queue as last reported and the commands waiting on the ground;
the coverage curve, metres driven, collisions, stuck steps, the events, the newest map seen
from above with the path. Commands are composed from the allowlist
(:mod:`mission.link.commands`, the rover's own list once it came down) and follow their
stages: queued on the ground, radiated, acknowledged executed or rejected with the reason.

The page is three static files (``console_page/``: HTML, CSS and plain JavaScript, no build
step) and a JSON interface, all from this module, on Python's standard HTTP server:

- ``GET /api/state``: :meth:`GroundStore.state`; the page polls it. Every browser and every
  reload draws the same, because the state is the station's, not the page's;
- ``GET /api/map``: the newest map snapshot (x, y, z, thinned) and the path;
- ``POST /api/commands`` with ``{"line": "pause"}``: the command is checked against the
  allowlist (the page checks first; this is the check that counts), queued, and answered 202
  with its id, or 400 with the reason it is refused (nothing is queued then).

Access: on loopback (the default) any local process may use it, as it may use the terminal
station. Beyond loopback the console needs a token (``--web-token-file``: the browser opens
``/?token=...`` once and keeps a cookie) or a client certificate from the mission's CA
(``--web-client-ca`` with ``--web-cert``/``--web-key`` for HTTPS: the station's own
certificate, which ``rovergate credentials`` makes for TLS clients). Requests whose Host is not
the console's own are refused on loopback (a web page elsewhere cannot reach it by rebinding a
name to 127.0.0.1), and a command must come as JSON from the console's own origin (a form on
another site cannot post one).
"""

from __future__ import annotations

import hmac
import http.server
import ipaddress
import json
import logging
import ssl
import threading
from collections.abc import Callable
from dataclasses import dataclass
from http import HTTPStatus
from importlib import resources
from pathlib import Path
from typing import Any, Protocol
from urllib.parse import parse_qs, urlsplit

from mission.link.commands import CommandError
from mission.link.store import GroundStore
from rovergate.errors import ConfigError
from rovergate.types import GroundCommand


@dataclass(frozen=True)
class ConsoleConfig:
    """Where the console listens and who it lets in (``rovergate ground``'s --web-* flags)."""

    host: str = "127.0.0.1"
    port: int = 0
    token_file: Path | None = None
    cert: Path | None = None
    key: Path | None = None
    client_ca: Path | None = None


class Station(Protocol):
    """What the console needs of the ground station (:class:`mission.link.ground.GroundStation`)."""

    store: GroundStore

    def accept(self, line: str) -> GroundCommand:
        """Check, number and queue a typed command; CommandError says why it is refused."""
        ...

PAGE_FILES = {"/": ("index.html", "text/html; charset=utf-8"),
              "/console.js": ("console.js", "text/javascript; charset=utf-8"),
              "/console.css": ("console.css", "text/css; charset=utf-8")}
COOKIE = "rovergate_console"
MAX_BODY = 4096
MIN_TOKEN = 16


def on_loopback(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        return False


def read_token(path: Path) -> str:
    """The console's token from its file; ConfigError in one line when it is unusable."""
    try:
        token = Path(path).read_text().strip()
    except OSError as exc:
        raise ConfigError(f"--web-token-file {path}: cannot read it ({exc.strerror}); write "
                          "a random line of at least 16 characters into it, e.g. `python -c "
                          "'import secrets; print(secrets.token_urlsafe())' > FILE`") from None
    if len(token) < MIN_TOKEN or not token.isprintable() or " " in token:
        raise ConfigError(f"--web-token-file {path}: the token must be one line of at least "
                          f"{MIN_TOKEN} printable characters without spaces; make one with "
                          "`python -c 'import secrets; print(secrets.token_urlsafe())'`")
    return token


def check_web(cfg: ConsoleConfig) -> None:
    """The console's flags, checked before anything starts (one line naming the fault)."""
    if not 0 <= cfg.port <= 65535:
        raise ConfigError(f"--web-port {cfg.port}: a port is 0 (a free one) to 65535")
    if (cfg.cert is None) != (cfg.key is None):
        raise ConfigError("--web-cert and --web-key go together (the console's HTTPS "
                          "certificate and its private key)")
    client_ca = cfg.client_ca
    if client_ca is not None and cfg.cert is None:
        raise ConfigError("--web-client-ca asks browsers for a client certificate, which "
                          "needs HTTPS: pass --web-cert and --web-key too")
    if cfg.token_file is not None:
        read_token(cfg.token_file)
    if not on_loopback(cfg.host) and cfg.token_file is None and client_ca is None:
        raise ConfigError(
            f"--web-host {cfg.host} is beyond loopback, and the console can command the "
            "rover: pass --web-token-file FILE (with --web-cert/--web-key to keep the token "
            "off the wire), or --web-client-ca DIR/station/ca.pem with --web-cert/--web-key "
            "(browsers then present the station's certificate); or serve on 127.0.0.1 and "
            "reach it through `ssh -L`")


class Console:
    """The console's HTTP server, on a thread of the ground station's process."""

    def __init__(self, station: Station, cfg: ConsoleConfig,
                 enqueue: Callable[[GroundCommand], None], log: logging.Logger) -> None:
        check_web(cfg)
        self.station = station
        self.cfg = cfg
        self.enqueue = enqueue
        self.log = log
        self.token = read_token(cfg.token_file) if cfg.token_file else None
        self.refused = 0
        """Requests refused (no token, a foreign host or origin, a malformed body)."""
        self._refused_from: set[str] = set()
        self.pages = {path: resources.files("mission.link").joinpath(
            "console_page", name).read_bytes() for path, (name, _) in PAGE_FILES.items()}
        self.server = http.server.ThreadingHTTPServer((cfg.host, cfg.port),
                                                      self._handler())
        self.server.daemon_threads = True
        self.scheme = "http"
        if cfg.cert is not None and cfg.key is not None:
            context = ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER)
            try:
                context.load_cert_chain(cfg.cert, cfg.key)
                if cfg.client_ca is not None:
                    context.load_verify_locations(cfg.client_ca)
                    context.verify_mode = ssl.CERT_REQUIRED
            except (OSError, ssl.SSLError) as exc:
                self.server.server_close()
                raise ConfigError(f"--web-cert/--web-key: cannot load them ({exc}); give a "
                                  "PEM certificate and its key") from None
            self.server.socket = context.wrap_socket(self.server.socket, server_side=True)
            self.scheme = "https"
        self.port = int(self.server.server_address[1])
        host = cfg.host if ":" not in cfg.host else f"[{cfg.host}]"
        self.url = f"{self.scheme}://{host}:{self.port}/"
        self._allowed_hosts = {f"{h}:{self.port}" for h in
                               (host, "localhost", "127.0.0.1", "[::1]")}
        self._thread: threading.Thread | None = None

    def start(self) -> None:
        self._thread = threading.Thread(target=self.server.serve_forever, name="console",
                                        daemon=True)
        self._thread.start()
        access = ("loopback only" if on_loopback(self.cfg.host) and self.token is None
                  else "token required" if self.token else "client certificate required")
        self.log.info("console on %s (%s)", self.url, access)

    def stop(self) -> None:
        self.server.shutdown()
        self.server.server_close()
        if self._thread is not None:
            self._thread.join(10)

    # --- requests ---------------------------------------------------------------------------

    def _refuse(self, address: str, why: str) -> None:
        self.refused += 1
        if address not in self._refused_from:  # once per client, not once per poll
            self._refused_from.add(address)
            self.log.warning("console: refused a request from %s: %s", address, why)

    def _handler(self) -> type[http.server.BaseHTTPRequestHandler]:
        console = self

        class Handler(http.server.BaseHTTPRequestHandler):
            server_version = "rovergate-console"
            protocol_version = "HTTP/1.1"

            def log_message(self, format: str, *args: Any) -> None:
                pass  # the station's log says what matters; polls would drown it

            def _send(self, status: int, body: bytes, content_type: str,
                      headers: dict[str, str] | None = None) -> None:
                self.send_response(status)
                self.send_header("Content-Type", content_type)
                self.send_header("Content-Length", str(len(body)))
                self.send_header("Cache-Control", "no-store")
                self.send_header("X-Content-Type-Options", "nosniff")
                self.send_header("Content-Security-Policy",
                                 "default-src 'self'; img-src 'self' data:")
                for k, v in (headers or {}).items():
                    self.send_header(k, v)
                self.end_headers()
                if self.command != "HEAD":
                    self.wfile.write(body)

            def _json(self, status: int, value: Any) -> None:
                self._send(status, json.dumps(value, separators=(",", ":")).encode(),
                           "application/json")

            def _error(self, status: int, why: str) -> None:
                self._json(status, {"error": why})

            def _allowed(self) -> bool:
                """Host, then token: False (and answered) when the request is refused."""
                address = self.client_address[0]
                host = self.headers.get("Host", "")
                if on_loopback(console.cfg.host) and host not in console._allowed_hosts:
                    console._refuse(address, f"Host {host!r} is not the console's")
                    self._error(HTTPStatus.MISDIRECTED_REQUEST,
                                f"this console answers only to {console.url}")
                    return False
                if console.token is None:
                    return True
                given = self.headers.get("Authorization", "").removeprefix("Bearer ").strip()
                for part in self.headers.get("Cookie", "").split(";"):
                    name, _, value = part.strip().partition("=")
                    if name == COOKIE:
                        given = given or value
                if given and hmac.compare_digest(given.encode(), console.token.encode()):
                    return True
                console._refuse(address, "no valid token")
                self._error(HTTPStatus.UNAUTHORIZED,
                            "this console needs its token: open "
                            f"{console.url}?token=TOKEN once (the station's --web-token-file)")
                return False

            def do_GET(self) -> None:  # noqa: N802 -- the standard library's name
                url = urlsplit(self.path)
                token = parse_qs(url.query).get("token", [""])[0]
                if url.path == "/" and token and console.token is not None and \
                        hmac.compare_digest(token.encode(), console.token.encode()):
                    secure = "; Secure" if console.scheme == "https" else ""
                    self._send(HTTPStatus.SEE_OTHER, b"", "text/plain", {
                        "Location": "/", "Set-Cookie":
                        f"{COOKIE}={token}; HttpOnly; SameSite=Strict; Path=/{secure}"})
                    return
                if not self._allowed():
                    return
                if url.path in PAGE_FILES:
                    self._send(HTTPStatus.OK, console.pages[url.path], PAGE_FILES[url.path][1])
                elif url.path == "/api/state":
                    state = console.station.store.state()
                    state["console"] = {"refused": console.refused}
                    self._json(HTTPStatus.OK, state)
                elif url.path == "/api/map":
                    self._json(HTTPStatus.OK, console.station.store.map_snapshot())
                else:
                    self._error(HTTPStatus.NOT_FOUND, f"no {url.path} here")

            do_HEAD = do_GET  # noqa: N815

            def do_POST(self) -> None:  # noqa: N802
                if not self._allowed():
                    return
                address = self.client_address[0]
                if urlsplit(self.path).path != "/api/commands":
                    self._error(HTTPStatus.NOT_FOUND, f"no {self.path} here")
                    return
                origin = self.headers.get("Origin")
                if origin is not None and urlsplit(origin).netloc != self.headers.get("Host"):
                    console._refuse(address, f"a command from the origin {origin!r}")
                    self._error(HTTPStatus.FORBIDDEN, "commands come from the console's own "
                                "page only")
                    return
                if self.headers.get_content_type() != "application/json":
                    console._refuse(address, "a command not sent as JSON")
                    self._error(HTTPStatus.UNSUPPORTED_MEDIA_TYPE,
                                'send {"line": "COMMAND"} as application/json')
                    return
                try:
                    length = int(self.headers.get("Content-Length", "0"))
                except ValueError:
                    length = -1
                if not 0 < length <= MAX_BODY:
                    console._refuse(address, f"a command body of {length} bytes")
                    self._error(HTTPStatus.BAD_REQUEST,
                                f"a command is a JSON body of 1 to {MAX_BODY} bytes")
                    self.close_connection = True
                    return
                try:
                    body = json.loads(self.rfile.read(length))
                    line = body["line"]
                    if not isinstance(line, str):
                        raise TypeError("line is not a string")
                except (ValueError, KeyError, TypeError) as exc:
                    console.refused += 1
                    self._error(HTTPStatus.BAD_REQUEST,
                                f'send {{"line": "COMMAND"}} ({type(exc).__name__})')
                    return
                try:
                    command = console.station.accept(line)
                except CommandError as exc:
                    console.log.info("console: refused %r: %s", line[:80], exc)
                    self._error(HTTPStatus.BAD_REQUEST, str(exc))
                    return
                console.enqueue(command)
                self._json(HTTPStatus.ACCEPTED, {"id": command.id})

        return Handler
