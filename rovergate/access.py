"""Who may do what on the rover's two Zenoh networks: Zenoh access control, as plain data.

**The rover network** is the mission manager's session and the module processes. The modules
join it as Zenoh clients on a Unix socket in a directory only the mission's user can open
(:mod:`mission.runtime.process_set`); no module listens on anything. The mission manager's session
is the network's one listener that another machine can reach (``--listen``), and its access
control gives every link over ``unixsock-stream`` full rights and every other link (TCP,
TLS, QUIC, WebSocket, ...) read-only rights (:func:`rover_network`):

- it may subscribe, query and watch liveliness: it receives what is published, replies,
  and the modules' liveliness tokens;
- it may not put or delete (so it cannot publish a status, a path or a sensor sample),
  declare a queryable or reply (so it cannot answer a journal or truth query), or declare a
  liveliness token (so it cannot pose as a module);
- it may not query ground truth, and no truth reply, sample or queryable goes out to it.

Zenoh 1.10 sends nothing on the wire when a publisher is declared (only its puts), so "no
publisher" is enforced as "no put and no delete".

Zenoh matches a query's key expression against the rules as a whole: a deny on
``rover/truth/**`` stops a query for ``rover/truth/x`` but not one for ``rover/**``, whose
truth replies are therefore denied on their way out instead (egress ``reply``).

**The ground network** is the bridge's session (:mod:`mission.link.bridge`) and the ground
station. The station may put only on the uplink and the acknowledgement keys, subscribe only
to the downlink and the transmitter's reports of what it radiated, and declare only its own
liveliness token (:func:`ground_network`); with
credentials, only a link whose certificate names the station has even that.
"""

from __future__ import annotations

from typing import Any

from rovergate.keys import Keys

ALL = ("put", "delete", "declare_subscriber", "query", "reply", "declare_queryable",
       "liveliness_token", "liveliness_query", "declare_liveliness_subscriber")
"""Every kind of message Zenoh's access control governs (1.10)."""

READ_INGRESS = ("declare_subscriber", "query", "declare_liveliness_subscriber",
                "liveliness_query")
"""What a read-only remote may send in: interest, never data."""
READ_EGRESS = ("put", "delete", "reply", "declare_queryable", "liveliness_token")
"""What may go out to a read-only remote: the data it asked for."""

MODULE_PROTOCOL = "unixsock-stream"
"""The rover network's own transport (every module's link to the mission manager)."""
OTHER_PROTOCOLS = ("tcp", "udp", "tls", "quic", "ws", "serial", "unixpipe", "vsock")
"""Every other link protocol Zenoh 1.10 knows: read-only on the rover network."""


def _rule(rule_id: str, messages: tuple[str, ...], flows: tuple[str, ...], permission: str,
          keys: tuple[str, ...]) -> dict[str, Any]:
    return {"id": rule_id, "messages": list(messages), "flows": list(flows),
            "permission": permission, "key_exprs": list(keys)}


def rover_network(namespace: str) -> dict[str, Any]:
    """The ``access_control`` section of the mission manager's session (module docstring)."""
    truth = (f"{namespace}/truth/**",)
    return {
        "enabled": True,
        "default_permission": "deny",
        "rules": [
            _rule("modules", ALL, ("ingress", "egress"), "allow", ("**",)),
            _rule("remote-in", READ_INGRESS, ("ingress",), "allow", ("**",)),
            _rule("remote-out", READ_EGRESS, ("egress",), "allow", ("**",)),
            _rule("remote-no-truth-in", ("query",), ("ingress",), "deny", truth),
            _rule("remote-no-truth-out", ("reply", "put", "delete", "declare_queryable"),
                  ("egress",), "deny", truth),
        ],
        "subjects": [{"id": "modules", "link_protocols": [MODULE_PROTOCOL]},
                     {"id": "remote", "link_protocols": list(OTHER_PROTOCOLS)}],
        "policies": [
            {"id": "modules-all", "rules": ["modules"], "subjects": ["modules"]},
            {"id": "remote-read-only", "subjects": ["remote"],
             "rules": ["remote-in", "remote-out", "remote-no-truth-in", "remote-no-truth-out"]},
        ],
    }


def ground_network(namespace: str, station_names: tuple[str, ...] = ()) -> dict[str, Any]:
    """The ``access_control`` section of the bridge's session. ``station_names``: the
    certificate common names of the stations (mutual TLS); empty: any link (only for a link
    without credentials, which listens on loopback only:
    :func:`mission.link.bridge.check_ground_endpoints` refuses credentials without names)."""
    keys = Keys(namespace)
    station: dict[str, Any] = {"id": "station"}
    if station_names:
        station["cert_common_names"] = list(station_names)
    else:
        station["link_protocols"] = [MODULE_PROTOCOL, *OTHER_PROTOCOLS]
    return {
        "enabled": True,
        "default_permission": "deny",
        "rules": [
            _rule("station-sends", ("put",), ("ingress",), "allow",
                  (keys.key("uplink"), keys.key("downlink_ack"))),
            _rule("station-listens", ("declare_subscriber",), ("ingress",), "allow",
                  (keys.key("downlink"), keys.key("uplink_report"))),
            _rule("station-is-there", ("liveliness_token",), ("ingress",), "allow",
                  (keys.alive("station"),)),
            _rule("station-watches", ("declare_liveliness_subscriber", "liveliness_query"),
                  ("ingress",), "allow", (keys.alive("rover"),)),
            _rule("bridge-sends", ALL, ("egress",), "allow", (f"{namespace}/**",)),
        ],
        "subjects": [station],
        "policies": [{"id": "station", "subjects": ["station"],
                      "rules": ["station-sends", "station-listens", "station-is-there",
                                "station-watches", "bridge-sends"]}],
    }
