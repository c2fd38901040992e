"""Another machine: a subscriber in its own network namespace (its own host and address,
linked by a veth pair) connects to the mission over TCP and decodes the occupancy topics."""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
import warnings
from pathlib import Path

import pytest

from rovergate.session import free_loopback_port

ROVERGATE = [sys.executable, "-m", "mission.cli"]
SUBSCRIBER = Path(__file__).resolve().parent.parent / "examples" / "remote_subscriber.py"


pytestmark = pytest.mark.e2e


def _sh(*cmd: str) -> subprocess.CompletedProcess:
    return subprocess.run(list(cmd), capture_output=True, text=True, timeout=30)


def _make_namespace(tag: str) -> tuple[str, str, str] | str:
    """(namespace, host address, namespace address), or why one cannot be made here."""
    if shutil.which("ip") is None:
        return "the `ip` tool (iproute2) is not installed"
    ns, host_if, ns_if = f"rg{tag}", f"rgh{tag}", f"rgn{tag}"
    octet = int(tag) % 250 + 1
    host_ip, ns_ip = f"10.231.{octet}.1", f"10.231.{octet}.2"
    steps = [("ip", "netns", "add", ns),
             ("ip", "link", "add", host_if, "type", "veth", "peer", "name", ns_if),
             ("ip", "link", "set", ns_if, "netns", ns),
             ("ip", "addr", "add", f"{host_ip}/30", "dev", host_if),
             ("ip", "link", "set", host_if, "up"),
             ("ip", "netns", "exec", ns, "ip", "addr", "add", f"{ns_ip}/30", "dev", ns_if),
             ("ip", "netns", "exec", ns, "ip", "link", "set", ns_if, "up"),
             ("ip", "netns", "exec", ns, "ip", "link", "set", "lo", "up")]
    for step in steps:
        r = _sh(*step)
        if r.returncode != 0:
            _remove_namespace(ns, host_if)
            return f"`{' '.join(step)}` failed: {r.stderr.strip() or r.returncode}"
    return ns, host_ip, ns_ip


def _remove_namespace(ns: str, host_if: str) -> None:
    _sh("ip", "link", "del", host_if)
    _sh("ip", "netns", "del", ns)


def test_subscriber_on_another_host_decodes_the_occupancy(tmp_path: Path):
    tag = str(os.getpid() % 10000)
    made = _make_namespace(tag)
    port = free_loopback_port()
    if isinstance(made, str):
        warnings.warn(f"network namespaces cannot be made here ({made}); the same subscriber "
                      "runs on loopback instead", stacklevel=1)
        listen, prefix, where = "127.0.0.1", [], "loopback"
    else:
        ns, listen, ns_ip = made
        prefix, where = ["ip", "netns", "exec", ns], ns_ip
    try:
        mission = subprocess.Popen(
            [*ROVERGATE, "run", "--steps", "8", "--no-progress", "--out", str(tmp_path / "m"),
             "--listen", f"tcp/{listen}:{port}", "--contact.no-enabled"],
            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
        sub = subprocess.run(
            [*prefix, sys.executable, str(SUBSCRIBER), "--connect", f"tcp/{listen}:{port}",
             "--count", "3", "--timeout-s", "120"], capture_output=True, text=True, timeout=180)
        _, err = mission.communicate(timeout=180)
        assert mission.returncode == 0, err[-3000:]
        assert sub.returncode == 0, sub.stdout[-2000:] + sub.stderr[-2000:]
        maps = re.findall(r"planner map step (\d+): (\d+) points \((\d+) observed", sub.stdout)
        assert len(maps) >= 3, sub.stdout
        assert all(int(n) > 0 and int(obs) == int(n) for _, n, obs in maps)  # obs condition
        assert "application/cdr;rovergate_msgs/msg/CloudUpdate" in sub.stdout
        assert re.search(r"surface step \d+: \d+ points", sub.stdout)
        if prefix:
            # The subscriber really was another host: its only address outside loopback is
            # the namespace's end of the veth pair.
            addrs = _sh(*prefix, "ip", "-4", "-o", "addr").stdout
            assert where in addrs and listen not in addrs
    finally:
        if not isinstance(made, str):
            _remove_namespace(made[0], f"rgh{tag}")
