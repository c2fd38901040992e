"""The link to the ground: contact plan, the onboard store-and-forward queue, commands."""

from __future__ import annotations

import contextlib
import json
import os
import re
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest
import tyro
import zenoh
from conftest import ROVERGATE, LinkedMission, RovergateProcess, run_cli

from mission.link.bridge import LINK_FILE, check_ground_endpoints, connectable, loopback
from mission.link.contact import ContactPlan, ContactPlanError
from mission.link.downlink import DownlinkQueue
from mission.link.ground import GroundConfig, LinkFileError, gaps, parse_command, resolve_link
from mission.link.operations import CommandError, apply_settings, choose_planner
from mission.run import check_runnable
from mission.runtime.process_set import program_argv
from rovergate.config import ContactConfig, MissionConfig, check_values
from rovergate.errors import ConfigError
from rovergate.node import cdr_encoding
from rovergate.session import free_loopback_port


def test_periodic_and_explicit_windows():
    plan = ContactPlan(ContactConfig(period_steps=25, window_steps=5, first_window_step=0))
    assert [t for t in range(60) if plan.is_open(t)] == [*range(5), *range(25, 30),
                                                         *range(50, 55)]
    assert plan.next_open(3) == 3 and plan.next_open(5) == 25 and plan.next_open(49) == 50
    assert plan.windows_between(0, 60) == [(0, 5), (25, 30), (50, 55)]
    explicit = ContactPlan(ContactConfig(windows=("10+5", "40+3")))
    assert explicit.next_open(0) == 10 and explicit.next_open(16) == 40
    assert explicit.next_open(43) is None
    assert explicit.windows_between(0, 100) == [(10, 15), (40, 43)]


def test_the_end_of_a_mission_always_has_a_way_down():
    # Explicit windows that end with the mission: the link is then held open.
    plan = ContactPlan(ContactConfig(windows=("0+60",), light_time_s=90, step_s=60))
    assert "held open" in plan.end_of_mission(60, 200)
    assert plan.next_open(61) is None and not plan.is_open(61)
    plan.hold_open(61)
    assert plan.is_open(61) and plan.is_open(500) and plan.next_open(70) == 70
    assert plan.is_open(10) and not plan.is_open(60)  # the plan itself is unchanged
    # Periodic windows go on after the mission; one too far for the round trip is refused.
    periodic = ContactPlan(ContactConfig(period_steps=25, window_steps=5))
    assert "the next at step 100" in periodic.end_of_mission(90, 200)
    sparse = ContactPlan(ContactConfig(period_steps=300, window_steps=5, light_time_s=90,
                                       step_s=60))
    with pytest.raises(ContactPlanError, match="could never reach the ground: after the last "
                                               "step a window can be 296 steps away"):
        sparse.end_of_mission(100, 300)  # a pause can put the end just after a window
    assert "the next at step 300" in sparse.end_of_mission(100, 400)
    # Held open, the round trip itself must fit.
    far = ContactPlan(ContactConfig(windows=("0+10",), light_time_s=6000, step_s=60))
    with pytest.raises(ContactPlanError, match="a round trip takes 202 steps"):
        far.end_of_mission(10, 200)


def test_light_time_and_rate_in_steps():
    plan = ContactPlan(ContactConfig(step_s=60, light_time_s=90, downlink_kbps=128))
    assert plan.light_steps == 2  # 1.5 steps, rounded up to the next step boundary
    assert plan.bytes_per_step == 128_000 // 8 * 60
    assert ContactPlan(ContactConfig(light_time_s=0)).light_steps == 0


@pytest.mark.parametrize("kwargs, match", [
    ({"windows": ("10-5",)}, "START\\+DURATION"),
    ({"window_steps": 0}, "window-steps"),
    ({"period_steps": 3, "window_steps": 5}, "period-steps"),
    ({"step_s": 0}, "step-s"),
])
def test_bad_contact_plans_say_how_to_fix_them(kwargs, match):
    with pytest.raises(ContactPlanError, match=match):
        ContactPlan(ContactConfig(**kwargs))


def _fill(q: DownlinkQueue, steps: int) -> None:
    for t in range(steps):
        q.put("status", "rovergate_msgs/msg/MissionStatus", t, b"s" * 100)
        q.put("pose", "geometry_msgs/msg/PoseStamped", t, b"p" * 100)


def test_queue_radiates_by_priority_and_numbers_contiguously(tmp_path: Path):
    q = DownlinkQueue(tmp_path / "q.sqlite")
    _fill(q, 3)
    q.put("map", "sensor_msgs/msg/PointCloud2", 1, b"m1" * 100)
    q.put("map", "sensor_msgs/msg/PointCloud2", 2, b"m2" * 100)  # supersedes the first
    q.put("event", "rovergate_msgs/msg/MissionEvent", 2, b"e" * 50)
    items = q.take(10_000, now_s=0.0, due_s=100.0)
    assert [i.kind for i in items] == ["event", "status", "status", "status", "pose", "pose",
                                       "pose", "map"]
    assert [i.seq for i in items] == list(range(1, 9))
    assert items[-1].payload == b"m2" * 100
    # Nothing more to send until the acknowledgements are due.
    assert q.take(10_000, now_s=50.0, due_s=150.0) == []
    assert q.ack([1, 2, 3]) == 3
    again = q.take(10_000, now_s=100.0, due_s=200.0)  # the rest is due: sent again
    assert [i.seq for i in again] == [4, 5, 6, 7, 8]  # with the same numbers
    q.ack([i.seq for i in again])
    assert len(q) == 0 and q.unacked() == 0


def test_queue_budget_stops_at_the_first_item_that_does_not_fit(tmp_path: Path):
    q = DownlinkQueue(tmp_path / "q.sqlite")
    q.put("status", "t", 0, b"x" * 300)
    q.put("status", "t", 1, b"x" * 300)
    q.put("pose", "t", 0, b"x" * 10)
    assert [i.step for i in q.take(500, 0.0, 1.0)] == [0]
    assert [i.kind for i in q.take(1000, 0.0, 1.0)] == ["status", "pose"]


def test_queue_bound_drops_old_samples_never_events_nor_radiated_items(tmp_path: Path):
    q = DownlinkQueue(tmp_path / "q.sqlite", max_bytes=2_000)
    q.put("event", "t", 0, b"e" * 1500)
    sent = q.take(10_000, 0.0, 1e9)
    assert [i.kind for i in sent] == ["event"]
    _fill(q, 20)  # 4000 bytes of samples into a 2000-byte bound
    q.put("event", "t", 20, b"e" * 100)
    assert q.nbytes() <= 2_000 + 100  # only the new event may stand over the bound
    kinds = [k for (k,) in q._db.execute("SELECT kind FROM items ORDER BY id")]
    assert kinds.count("event") == 2  # the radiated one is kept until acknowledged
    steps = [s for (s,) in q._db.execute(
        "SELECT step FROM items WHERE kind = 'status' ORDER BY id")]
    assert steps and steps == sorted(steps) and steps[-1] == 19  # the oldest went first
    assert q.dropped == 40 - len(steps) - len(
        [1 for (k,) in q._db.execute("SELECT kind FROM items") if k == "pose"])


_CRASH = """
import os, sys
from mission.link.downlink import DownlinkQueue
q = DownlinkQueue(sys.argv[1])
for t in range(50):
    q.put("status", "t", t, bytes(200))
q.take(2_000, 0.0, 10.0)   # radiates 10, numbered 1..10
print("ready", flush=True)
os.kill(os.getpid(), 9)     # the mission manager dies without closing anything
"""


def test_queue_survives_a_killed_mission_manager(tmp_path: Path):
    path = tmp_path / "q.sqlite"
    proc = subprocess.run([sys.executable, "-c", _CRASH, str(path)], capture_output=True,
                          text=True, timeout=60)
    assert proc.returncode == -9 and "ready" in proc.stdout
    q = DownlinkQueue(path)
    assert len(q) == 50 and q.unacked() == 10
    q.ack(list(range(1, 6)))
    items = q.take(100_000, 20.0, 30.0)
    # The unacknowledged five go again with their numbers; the rest continue the sequence.
    assert [i.seq for i in items] == list(range(6, 51))
    assert gaps({i.seq for i in items} | set(range(1, 6))) == []


def test_corrupt_queue_file_is_one_clear_line(tmp_path: Path):
    path = tmp_path / "q.sqlite"
    path.write_bytes(b"not a database at all" * 100)
    with pytest.raises(ConfigError, match="not a usable SQLite file.*move it away"):
        DownlinkQueue(path)


@pytest.mark.parametrize("line, verb, args", [
    ("pause", "pause", []),
    ("set gate.k=3 gate.epsilon_frac=0.05", "set", ["gate.k=3", "gate.epsilon_frac=0.05"]),
    ("condition gated", "condition", ["gated"]),
    ("planner frontier", "planner", ["frontier"]),
])
def test_ground_parses_commands(line, verb, args):
    c = parse_command(line, 7)
    assert (c.id, c.verb, c.args) == (7, verb, args)


@pytest.mark.parametrize("line", ["jump", "pause now", "set gate.k", "condition", "",
                                  "planner cmd python my_planner.py --x 'a b'"])
def test_ground_refuses_malformed_commands(line):
    with pytest.raises(ValueError):
        parse_command(line, 1)


@pytest.mark.parametrize("args, commands", [
    (["--send", "pause", "--send", "resume"], ["pause", "resume"]),  # not only the last
    (["--send", "set gate.k=3", "pause"], ["set gate.k=3", "pause"]),
    (["--send", "set gate.k=3", "pause", "--send", "resume"], ["set gate.k=3", "pause",
                                                                 "resume"]),
    ([], []),
])
def test_ground_sends_every_command_given(args, commands):
    assert tyro.cli(GroundConfig, args=args).commands == commands


#: An endpoint that is only parsed here, never opened or connected to.
PARSED_ONLY = "tcp/rover.invalid:7448"


def _link_file(mission: Path, **fields) -> None:
    link = {"endpoints": [PARSED_ONLY], "ground_namespace": "earth",
            "rover_namespace": "rover", "pid": os.getpid(), "host": socket.gethostname(),
            "started_at": "2025-01-01T00:00:00+00:00", **fields}
    mission.mkdir(exist_ok=True)
    (mission / LINK_FILE).write_text(json.dumps(link))


def test_ground_finds_the_link_in_the_missions_directory(tmp_path: Path):
    assert GroundConfig().mission == MissionConfig().out  # `rovergate run`'s default --out
    _link_file(tmp_path)
    cfg = resolve_link(GroundConfig(mission=tmp_path))
    assert (cfg.connect, cfg.namespace) == ((PARSED_ONLY,), "earth")
    given = resolve_link(GroundConfig(mission=tmp_path, connect=("tcp/ground.invalid:7448",)))
    assert (given.connect, given.namespace) == (("tcp/ground.invalid:7448",), "ground")  # wins
    assert resolve_link(GroundConfig(mission=tmp_path, namespace="mars")).namespace == "mars"


def _dead_pid() -> int:
    proc = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"],
                          capture_output=True, text=True, timeout=60)
    return int(proc.stdout)


@pytest.mark.parametrize("content, why", [
    (None, "does not exist"),
    ("{not json", "cannot be read as JSON"),
    ('{"endpoints": [], "ground_namespace": "ground"}', "is not a mission's ground link file"),
    ('["tcp/rover.invalid:7448"]', "is not a mission's ground link file"),
    ("dead", "no longer running"),
])
def test_ground_without_a_usable_link_file_says_so_in_one_line(tmp_path: Path, content, why):
    if content == "dead":
        _link_file(tmp_path, pid=_dead_pid())
    elif content is not None:
        (tmp_path / LINK_FILE).write_text(content)
    with pytest.raises(LinkFileError) as e:
        resolve_link(GroundConfig(mission=tmp_path))
    message = str(e.value)
    assert message.startswith(str(tmp_path / LINK_FILE)) and why in message
    assert message.endswith("start a mission first, or pass --mission OUT or --connect "
                            "tcp/HOST:PORT") and "\n" not in message


@pytest.mark.parametrize("listen", [(), ("tcp/127.0.0.1:0",)])
def test_bridge_takes_a_free_port_and_says_where_while_the_link_is_up(tmp_path: Path, listen):
    from mission.link.bridge import GroundBridge
    bridge = GroundBridge(ContactConfig(ground_listen=listen), tmp_path)
    try:
        link = json.loads((tmp_path / LINK_FILE).read_text())
        (endpoint,) = link["endpoints"]
        assert re.fullmatch(r"tcp/127\.0\.0\.1:\d+", endpoint) and not endpoint.endswith(":0")
        assert (link["pid"], link["ground_namespace"], link["rover_namespace"]) == (
            os.getpid(), "ground", "rover")
        assert tuple(link["endpoints"]) == bridge.endpoints
        # Its port is taken now: a mission asking for that very endpoint is refused in a line.
        with pytest.raises(ConfigError, match=r"^the ground endpoint .* could not be "
                                              r"opened .*leave --contact.ground-listen out"):
            GroundBridge(ContactConfig(ground_listen=(endpoint,)), tmp_path / "other")
    finally:
        bridge.close()
    assert not (tmp_path / LINK_FILE).exists()


def test_bridge_leaves_another_missions_link_file_alone(tmp_path: Path):
    from mission.link.bridge import GroundBridge
    bridge = GroundBridge(ContactConfig(), tmp_path)
    _link_file(tmp_path, pid=os.getpid() + 1)  # another mission, same --out, since
    bridge.close()
    assert json.loads((tmp_path / LINK_FILE).read_text())["pid"] == os.getpid() + 1


@pytest.mark.e2e
def test_ground_command_without_a_mission_is_one_line(tmp_path: Path):
    r = subprocess.run([*ROVERGATE, "ground", "--mission", str(tmp_path / "none"), "--out",
                        str(tmp_path / "g")], capture_output=True, text=True, timeout=120)
    assert r.returncode != 0 and r.stderr.count("\n") == 1, r.stderr
    assert r.stderr.startswith(f"error: {tmp_path / 'none' / LINK_FILE} does not exist")


@pytest.mark.parametrize("listen, connect", [
    ("tls/0.0.0.0:{port}", "tls/127.0.0.1:{port}"),
    ("tcp/[::]:{port}", "tcp/[::1]:{port}"),
    ("tls/127.0.0.1:{port}#iface=lo", "tls/127.0.0.1:{port}#iface=lo"),
    ("tls/rover.example:{port}", "tls/rover.example:{port}"),
])
def test_the_link_file_names_an_address_a_station_can_connect_to(listen, connect):
    port = free_loopback_port()  # only parsed here; a port of the test's own all the same
    assert connectable(listen.format(port=port)) == connect.format(port=port)


def test_the_station_refuses_what_the_rover_would_before_sending_it(tmp_path: Path):
    """`--send "set gate.k=500"` is one line and exit 2 before anything starts (it used to go
    up and be refused in flight); a station that never reaches a mission stops at its
    --timeout-s even with a command waiting to go up, and says so."""
    r = subprocess.run([*ROVERGATE, "ground", "--connect", "tcp/127.0.0.1:9", "--out",
                        str(tmp_path / "g"), "--send", "set gate.k=500"],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and r.stderr.count("\n") == 1, r.stderr
    assert "--send 'set gate.k=500': gate.k must be between 1 and 100, got '500'" in r.stderr
    assert not (tmp_path / "g").exists()
    port = free_loopback_port()  # nothing listens there
    t0 = time.monotonic()
    r = subprocess.run([*ROVERGATE, "ground", "--connect", f"tcp/127.0.0.1:{port}", "--out",
                        str(tmp_path / "g"), "--send", "pause", "--no-stdin", "--timeout-s",
                        "3"], capture_output=True, text=True, timeout=120)
    assert time.monotonic() - t0 < 60  # not stuck waiting for a bridge that never comes
    assert r.returncode == 1 and "was never on the link in 3 s" in r.stderr, r.stderr[-2000:]
    assert "command 1 not sent (pause)" in r.stderr


def test_settings_change_in_flight_only_where_allowed():
    cfg, modules = apply_settings(MissionConfig(), ["gate.k=3", "gate.epsilon_frac=0.05"])
    assert (cfg.gate.k, cfg.gate.epsilon_frac, modules) == (3, 0.05, {"gate"})
    cfg, modules = apply_settings(MissionConfig(), ["planner.n_candidates=16",
                                                    "planner.max_step_m=2"])
    assert (cfg.planner.n_candidates, cfg.planner.max_step_m) == (16, 2.0)
    assert modules == {"planner"}
    for refused in ("sensor.width_px=640", "planner.command=sh -c 'touch x'",
                    "planner.programs=x", "planner.name=beam", "planner.flyer_margin_m=0",
                    "planner.known_free_only=false", "gate"):
        with pytest.raises(CommandError, match="cannot set .* in flight; settable: gate.k"):
            apply_settings(MissionConfig(), [refused])
    with pytest.raises(CommandError, match="gate.k takes an integer, got 'three'"):
        apply_settings(MissionConfig(), ["gate.k=three"])
    with pytest.raises(CommandError, match="gate.k takes an integer, got 'true'"):
        apply_settings(MissionConfig(), ["gate.k=true"])
    with pytest.raises(CommandError, match="gate.k takes an integer, got '2.5'"):
        apply_settings(MissionConfig(), ["gate.k=2.5"])
    # Out of range, NaN and infinities are refused before any module restarts.
    for value in ("0", "101", "1e9"):
        with pytest.raises(CommandError, match="gate.k"):
            apply_settings(MissionConfig(), [f"gate.k={value}"])
    # Nothing the parser could choke on reaches it (an overflow or a recursion once ended
    # the mission at the step boundary).
    for value in ("1" + "0" * 400, "[" * 100_000, "0x10", "1_000"):
        with pytest.raises(CommandError, match="gate.epsilon_frac takes a number"):
            apply_settings(MissionConfig(), [f"gate.epsilon_frac={value}"])
    for value in ("0", "NaN", "Infinity", "-Infinity", "1e308"):
        with pytest.raises(CommandError, match="gate.epsilon_frac must be between"):
            apply_settings(MissionConfig(), [f"gate.epsilon_frac={value}"])


def test_the_ground_chooses_a_planner_by_name_never_a_command_line():
    cfg = MissionConfig()
    cfg.planner.programs = ("frontier=python examples/frontier_planner.py --radius 2",)
    assert choose_planner(cfg, "beam").planner.name == "beam"
    swapped = choose_planner(cfg, "frontier")
    assert swapped.planner.command == "python examples/frontier_planner.py --radius 2"
    back = choose_planner(swapped, "greedy")
    assert (back.planner.name, back.planner.command) == ("greedy", "")
    for name in ("cmd", "sh", "frontier2"):
        with pytest.raises(CommandError, match="choose one of: auto, beam, greedy, frontier"):
            choose_planner(cfg, name)
    # The program runs with the mission's own interpreter, whatever python is on the PATH.
    argv = program_argv(swapped.planner.command)
    assert argv == [sys.executable, "examples/frontier_planner.py", "--radius", "2"]
    assert program_argv("/opt/bin/planner -v") == ["/opt/bin/planner", "-v"]


@pytest.mark.parametrize("entries, why", [
    (("frontier",), "is not NAME=COMMAND"),
    (("=python x.py",), "is not NAME=COMMAND"),
    (("a b=python x.py",), "is not NAME=COMMAND"),
    (("f=python a.py", "f=python b.py"), "names 'f' twice"),
])
def test_bad_planner_programs_are_one_line(entries, why):
    cfg = MissionConfig()
    cfg.planner.programs = entries
    with pytest.raises(ConfigError, match=why):
        check_values(cfg)


def test_a_planner_program_may_not_take_a_built_in_name():
    cfg = MissionConfig()
    cfg.planner.programs = ("beam=python x.py",)
    with pytest.raises(ConfigError, match="'beam' is the name of a built-in or installed planner"):
        check_runnable(cfg)


# --- end to end: the process set, the bridge and a ground station, in Zenoh peer mode ------

EXAMPLES = Path(__file__).resolve().parent.parent / "examples"


@pytest.mark.e2e
def test_telemetry_crosses_blackouts_whole_and_commands_wait_for_a_window(tmp_path: Path):
    """Windows of 2 steps every 6, light time 1 step: four blackouts in 24 steps. Every
    status reaches the ground once, numbered without a gap; a command sent in a blackout
    executes at the next window's opening plus the light time."""
    steps = 24
    plan = ContactPlan(ContactConfig(period_steps=6, window_steps=2, first_window_step=2,
                                     light_time_s=60, step_s=60))
    m = LinkedMission(tmp_path, "--contact.period-steps", "6", "--contact.window-steps", "2",
                "--contact.first-window-step", "2", "--contact.light-time-s", "60",
                steps=steps)
    sent_at = m.wait_step(10)  # steps 10 and 11: a blackout (windows at 8-9 and 14-15)
    assert not plan.is_open(sent_at) and not plan.is_open(sent_at + 1)
    m.command("set planner.n_candidates=24")
    metrics, rows, ground_log = m.finish()
    seqs = [r["seq"] for r in rows]
    assert seqs == list(range(1, len(rows) + 1))  # no gap, no duplicate, in order
    status_steps = sorted(r["step"] for r in rows if r["kind"] == "status")
    assert status_steps == [*range(steps + 1), steps]  # every step, and the final status
    assert [r["state"] for r in rows if r["kind"] == "status"][-1] == "done"
    assert len(plan.windows_between(0, steps)) >= 4  # so at least three blackouts between
    # Radiated only inside windows.
    for r in rows:
        assert plan.is_open(int(r["radiated_s"] // 60)), r
    acks = [r for r in rows if r["kind"] == "command_ack"]
    assert len(acks) == 1 and acks[0]["state"] == "executed", acks
    expected = plan.next_open(sent_at + 1) + plan.light_steps
    assert acks[0]["executed_step"] == expected
    (command,) = metrics["link"]["commands"]
    assert command["step"] == expected and command["verb"] == "set"
    events = [r["event"] for r in rows if r["kind"] == "event"]
    assert events[0] == "mission-started" and "reconfigured" in events and \
        "mission-done" in events
    assert metrics["link"]["undelivered"] == 0
    assert "gaps: none" in ground_log


@pytest.mark.e2e
def test_the_readmes_tls_recipe_on_one_machine(tmp_path: Path):
    """`--contact.ground-listen tls/0.0.0.0:PORT` (every interface) and `rovergate ground
    --credentials DIR/station`: ground.json names 127.0.0.1, which the rover's certificate
    holds, and the station is on the link at once (it used to connect to 0.0.0.0, fail the
    certificate check and print a Zenoh timeout with a Rust source path after 19 s). A name
    the certificate does not hold is one line, within the station's --timeout-s."""
    m = LinkedMission(tmp_path, "--contact.ground-listen", "tls/0.0.0.0:0", steps=6)
    link = json.loads((m.out / LINK_FILE).read_text())
    assert link["listen"][0].startswith("tls/0.0.0.0:"), link
    port = link["listen"][0].rsplit(":", 1)[1]
    m.ground.wait_for_line("the rover's mission manager is on the link", 30)
    t0 = time.monotonic()
    r = subprocess.run([*ROVERGATE, "ground", "--connect", f"tls/127.0.0.2:{port}",
                        "--credentials", str(m.credentials["station"]), "--out",
                        str(tmp_path / "g2"), "--no-stdin", "--timeout-s", "3"],
                       capture_output=True, text=True, timeout=120)
    assert time.monotonic() - t0 < 60
    assert r.returncode == 2 and r.stderr.count("\n") == 1, r.stderr[-2000:]
    assert f"no TLS link to the mission at tls/127.0.0.2:{port} within 3 s" in r.stderr
    assert ".rs:" not in r.stderr
    metrics, rows, _ = m.finish()
    assert metrics["state"] == "done"
    assert [r["state"] for r in rows if r["kind"] == "status"][-1] == "done"


@pytest.mark.e2e
def test_planner_swapped_mid_mission_takes_over(tmp_path: Path):
    """A ground command replaces the built-in planner with a program that only knows zenoh
    and rosbags (examples/frontier_planner.py), named at launch; it plans every later step,
    run by the mission's own interpreter although its command line says python."""
    steps = 14
    m = LinkedMission(tmp_path, "--contact.period-steps", "4", "--contact.window-steps", "2",
                      "--contact.light-time-s", "0", "--planner.programs",
                      f"frontier=python {EXAMPLES / 'frontier_planner.py'}", steps=steps)
    m.wait_step(3)
    m.command("planner frontier")
    metrics, rows, _ = m.finish()
    (command,) = metrics["link"]["commands"]
    assert command["state"] == "executed", command
    swapped = command["step"]
    assert 4 <= swapped < steps
    log = (m.out / "logs" / "planner.log").read_text()
    planned = sorted(int(s) for s in re.findall(r"frontier planner: step (\d+)", log))
    assert planned == list(range(swapped, steps)), (swapped, planned)
    assert metrics["state"] == "done" and len(metrics["coverage"]) == steps + 1
    assert metrics["coverage"][-1] > metrics["coverage"][swapped]


@pytest.mark.e2e
def test_the_end_of_a_mission_reaches_the_ground_when_the_windows_end_with_it(
        tmp_path: Path):
    """--contact.windows 0+N for an N-step mission: the last items, the final status and the
    mission-done event come down over the link held open after the plan's last window."""
    steps = 10
    m = LinkedMission(tmp_path, "--contact.windows", f"0+{steps}", "--contact.light-time-s",
                      "60", steps=steps)
    metrics, rows, _ = m.finish()
    events = [r["event"] for r in rows if r["kind"] == "event"]
    assert "mission-done" in events, events
    statuses = [r for r in rows if r["kind"] == "status"]
    assert statuses[-1]["state"] == "done" and statuses[-1]["step"] == steps
    assert metrics["link"]["undelivered"] == 0
    assert metrics["link"]["drain_idle_steps"] < 20, metrics["link"]


@pytest.mark.e2e
def test_the_example_planner_explores(tmp_path: Path):
    """examples/frontier_planner.py, started as the README says, drives off on the default
    scene (its mast camera's blind band once held it turning in place: 0.0 m in 30 steps)."""
    r = run_cli("run", "--steps", "20", "--planner.command",
                f"python {EXAMPLES / 'frontier_planner.py'}", "--out", str(tmp_path / "f"),
                timeout=300)
    assert r.returncode == 0, r.stderr[-3000:]
    m = json.loads((tmp_path / "f" / "metrics.json").read_text())
    log = (tmp_path / "f" / "logs" / "planner.log").read_text()
    assert m["path_length_m"] > 20, m["path_length_m"]
    assert m["coverage"][-1] > m["coverage"][0] + 0.3, m["coverage"]
    assert log.count("turning in place") < 5 and m["stuck_steps"] == 0


@pytest.mark.e2e
def test_a_swap_that_does_not_come_up_is_rolled_back(tmp_path: Path):
    """A planner program that exits at once: the swap is undone, the acknowledgement says
    why, and the mission's numbers are those of a mission that never swapped."""
    steps = 12
    m = LinkedMission(tmp_path, "--contact.period-steps", "4", "--contact.window-steps", "2",
                      "--contact.light-time-s", "0", "--planner.programs",
                      "broken=python -c 'import sys; sys.exit(3)'", steps=steps)
    m.wait_step(3)
    m.command("planner broken")
    metrics, rows, _ = m.finish()
    (command,) = metrics["link"]["commands"]
    assert command["state"] == "rejected", command
    assert "did not come up with the new configuration (module 'planner' exited with code 3" \
        in command["detail"] and "the previous configuration runs on" in command["detail"]
    events = [r["event"] for r in rows if r["kind"] == "event"]
    assert "reconfiguration-rolled-back" in events and "mission-done" in events
    assert metrics["state"] == "done" and metrics["link"]["reconfigurations"] == []
    clean = run_cli("run", "--steps", str(steps), "--in-process", "--out", str(tmp_path / "i"),
                    timeout=300)
    assert clean.returncode == 0, clean.stderr[-3000:]
    i = json.loads((tmp_path / "i" / "metrics.json").read_text())
    assert metrics["coverage"] == i["coverage"]


#: A planner program that comes up (its liveliness token), then dies a moment later
#: ("dies") or never sends a path ("silent").
_FAULTY = """
import json, sys, time, zenoh
arg = sys.argv.index
conf = zenoh.Config()
conf.insert_json5("mode", '"client"')
conf.insert_json5("connect/endpoints", json.dumps([sys.argv[arg("--connect") + 1]]))
session = zenoh.open(conf)
token = session.liveliness().declare_token(sys.argv[arg("--namespace") + 1] + "/alive/planner")
time.sleep(1.0 if sys.argv[1] == "dies" else 600)
sys.exit(4)
"""


@pytest.mark.e2e
@pytest.mark.parametrize("fault, why", [
    ("dies", "exited with code 4 more than --max-restarts 1 times"),
    ("silent", "sent no rover/plan/path of step"),
])
def test_a_swap_that_comes_up_and_then_fails_is_rolled_back(tmp_path: Path, fault, why):
    """A planner program that comes up and then dies after each restart, or never sends a
    path: the planner is rolled back to the built-in one (and a later command's setting
    stays), the mission goes on to its end, and the ground hears why."""
    program = tmp_path / "faulty.py"
    program.write_text(_FAULTY)
    steps = 12
    m = LinkedMission(tmp_path, "--contact.period-steps", "4", "--contact.window-steps", "2",
                      "--contact.light-time-s", "0", "--max-restarts", "1",
                      "--step-timeout-s", "20", "--planner.programs",
                      f"faulty=python {program} {fault}", steps=steps)
    m.wait_step(3)
    m.command("planner faulty")
    m.command("set gate.k=4")
    metrics, rows, _ = m.finish()
    assert [c["state"] for c in metrics["link"]["commands"]] == ["executed", "executed"]
    rolled = [r for r in metrics["link"]["reconfigurations"] if r["verb"] == "rollback"]
    assert len(rolled) == 1 and why in rolled[0]["detail"], rolled
    assert "planner restarted with the previous one" in rolled[0]["detail"]
    events = [(r["event"], r.get("detail", "")) for r in rows if r["kind"] == "event"]
    assert any(e == "reconfiguration-rolled-back" and why in d for e, d in events), events
    assert metrics["state"] == "done" and len(metrics["coverage"]) == steps + 1
    last = max((tmp_path / "m").glob("config.*.json"), key=lambda p: int(p.suffixes[0][1:]))
    config = json.loads(last.read_text())
    assert config["planner"]["command"] == "" and config["gate"]["k"] == 4


@pytest.mark.e2e
def test_condition_change_pause_resume_and_abort_from_the_ground(tmp_path: Path):
    """The mission starts under obs; the ground switches it to the gated filter (the mapper
    and the gate restart with the model on and replay the past), pauses it, resumes it and
    aborts it."""
    m = LinkedMission(tmp_path, "--contact.period-steps", "4", "--contact.window-steps", "2",
                "--contact.light-time-s", "0", steps=60)
    m.wait_step(1)
    m.command("condition gated")
    changed = m.wait_for_row(r"command_ack .*\(condition\)",
                             lambda r: r.get("verb") == "condition")
    assert changed["state"] == "executed", changed
    m.command("pause")
    paused = m.wait_for_row(r"event .* paused", lambda r: r.get("event") == "paused")
    # While paused the mission publishes a keep-alive a second: after two of them, no tick
    # has gone past the held step.
    m.watcher.waiter.wait_for(lambda: m.watcher.states.count("paused") >= 2, 60,
                              "two 'paused' keep-alives")
    held = max(m.steps)
    m.command("resume")
    m.wait_for_row(r"event .* resumed", lambda r: r.get("event") == "resumed")
    m.command("abort")
    metrics, rows, _ = m.finish()
    assert metrics["state"] == "aborted" and len(metrics["coverage"]) < 61
    states = {c["verb"]: c["state"] for c in metrics["link"]["commands"]}
    assert states == {"condition": "executed", "pause": "executed", "resume": "executed",
                      "abort": "executed"}
    step = changed["executed_step"]
    predicted = metrics["predicted_points_per_step"]
    assert not any(predicted[:step]) and any(predicted[step:])  # the model runs from then on
    assert held == paused["step"]  # nothing moved while paused
    assert [r["state"] for r in rows if r["kind"] == "status"][-1] == "aborted"
    # The report says both conditions, and the aborted mission's map shows what it saw (it
    # was empty when the surface was kept only at the last step): an empty map has a few
    # hundred colours, the surface coloured by height tens of thousands.
    assert metrics["conditions"] == [[0, "obs"], [step, "gated"]]
    import matplotlib.image
    import numpy as np
    picture = matplotlib.image.imread(m.out / "map_topdown.png")[..., :3].reshape(-1, 3)
    assert len(np.unique((picture * 255).astype(np.uint8), axis=0)) > 2000


@pytest.mark.e2e
def test_two_missions_with_default_links_run_side_by_side(tmp_path: Path):
    """No fixed port: two missions started together with the default contact flags each open
    their link to the ground on a port of their own, and both end cleanly."""
    procs = [subprocess.Popen([*ROVERGATE, "run", "--steps", "2", "--no-progress", "--out",
                               str(tmp_path / name)],
                              stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
             for name in ("one", "two")]
    try:
        logs = [p.communicate(timeout=300)[1] for p in procs]
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
    for p, log in zip(procs, logs, strict=True):
        assert p.returncode == 0, log[-3000:]
    endpoints = [re.search(r"link to the ground on (tcp/127\.0\.0\.1:\d+) ", log).group(1)
                 for log in logs]
    assert endpoints[0] != endpoints[1]
    assert not any((tmp_path / name / LINK_FILE).exists() for name in ("one", "two"))


@pytest.mark.parametrize("endpoint, on_loopback", [
    ("tcp/127.0.0.1:0", True), ("tcp/[::1]:0", True), ("tcp/localhost:0", True),
    ("tcp/0.0.0.0:0", False), ("tcp/10.0.0.2:0", False), ("tcp/[::]:0", False),
    ("tcp/127.attacker.example:0", False), ("tcp/rover.local:0", False),
])
def test_without_credentials_the_ground_link_stays_on_loopback(endpoint, on_loopback):
    assert loopback(endpoint) is on_loopback
    if on_loopback:
        check_ground_endpoints((endpoint,), authenticated=False)
    else:
        with pytest.raises(ConfigError, match="beyond loopback.*rovergate credentials"):
            check_ground_endpoints((endpoint,), authenticated=False)
    with pytest.raises(ConfigError, match="use tls/HOST:PORT"):
        check_ground_endpoints((endpoint,), authenticated=True)
    check_ground_endpoints((endpoint.replace("tcp/", "tls/"),), authenticated=True)
    with pytest.raises(ConfigError, match="ground-stations is empty"):
        check_ground_endpoints((endpoint.replace("tcp/", "tls/"),), True, stations=())


@pytest.mark.e2e
def test_without_the_missions_credentials_no_command_reaches_the_rover(tmp_path: Path):
    """The ground link is mutual TLS under access control. Plain TCP, TLS without a client
    certificate, and a certificate from another CA get no link at all; a certificate the
    mission's CA signed for another name than the station's gets a link, and nothing it
    sends passes. Each one sends `planner cmd sh -c 'touch FILE' sh` and `pause` while the
    window is open: FILE never appears, no command reaches the rover, and the mission's
    numbers are a clean run's."""
    from mission.link.credentials import CredentialsConfig, create
    from rovergate.config import SessionConfig
    from rovergate.keys import Keys
    from rovergate.messages import encode
    from rovergate.session import TlsFiles, open_session, zenoh_config
    from rovergate.types import GroundCommand

    creds = create(CredentialsConfig(out=tmp_path / "c"))
    foreign = create(CredentialsConfig(out=tmp_path / "foreign"))  # another CA
    mallory = create(CredentialsConfig(out=tmp_path / "mallory", ca=creds["ca"],
                                       station_name="mallory"))
    steps, out, marker = 20, tmp_path / "m", tmp_path / "FILE"
    mission = RovergateProcess(["run", "--steps", str(steps), "--no-progress", "--out", str(out),
                       "--contact.credentials", str(creds["rover"]),
                       "--contact.windows", f"0+{steps}"])
    keys = Keys("ground")
    sessions = []
    try:
        mission.wait_for_line("link to the ground on")
        endpoint = json.loads((out / LINK_FILE).read_text())["endpoints"][0]
        plain = endpoint.replace("tls/", "tcp/")

        def files(d: Path, name: str) -> TlsFiles:
            return TlsFiles(d / "ca.pem", d / f"{name}.pem", d / f"{name}.key")
        # A link, and nothing passes: the rover's access control admits only `station`.
        intruder = open_session(SessionConfig(mode="peer", connect=(endpoint,)),
                                tls=files(mallory["station"], "station"))
        sessions.append(intruder)
        assert len(list(intruder.info.peers_zid())) == 1
        # No link at all: the session either fails to open or opens with no peer.
        unlinked = open_session(SessionConfig(mode="peer", connect=(plain,)))
        sessions.append(unlinked)
        assert list(unlinked.info.peers_zid()) == []
        with pytest.raises(ConfigError):
            open_session(SessionConfig(mode="client", connect=(plain,)))
        no_cert = zenoh.Config()
        no_cert.insert_json5("mode", '"client"')
        no_cert.insert_json5("connect/endpoints", json.dumps([endpoint]))
        no_cert.insert_json5("transport/link/tls", json.dumps(
            {"root_ca_certificate": str(creds["station"] / "ca.pem")}))
        with pytest.raises(zenoh.ZError):
            zenoh.open(no_cert)
        other_ca = zenoh_config(SessionConfig(mode="peer", connect=(endpoint,)),
                                tls=files(foreign["station"], "station"))
        other_ca.insert_json5("connect/timeout_ms", "2000")
        with pytest.raises(zenoh.ZError):
            zenoh.open(other_ca)
        assert mission.proc.poll() is None, "the mission ended before the attempts did"
        heard: list = []
        intruder.declare_subscriber(keys.key("downlink"), heard.append)
        for session in (intruder, unlinked):
            session.liveliness().declare_token(keys.alive("station"))
        sent = 0
        while mission.proc.poll() is None and sent < 2000:
            for session in (intruder, unlinked):
                for i, (verb, args) in enumerate((
                        ("planner", ["cmd", f"sh -c 'touch {marker}' sh"]),
                        ("pause", []), ("abort", []))):
                    session.put(keys.key("uplink"), encode("uplink", GroundCommand(
                        sent + i + 1, verb, args)), encoding=cdr_encoding("uplink"))
            sent += 3
            with contextlib.suppress(subprocess.TimeoutExpired):
                mission.proc.wait(0.02)  # paced, until the mission ends
        assert mission.finish(240) == 0, mission.text[-4000:]
    finally:
        for session in sessions:
            session.close()
        mission.kill()
    assert sent >= 30, sent
    assert not marker.exists()
    assert heard == []  # not even the downlink
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["state"] == "done" and metrics["link"]["commands"] == []
    assert metrics["link"]["dropped_ground_messages"] == 0  # denied before the bridge
    clean = run_cli("run", "--steps", str(steps), "--in-process", "--out", str(tmp_path / "i"),
                    timeout=300)
    assert clean.returncode == 0, clean.stderr[-3000:]
    assert (out / "coverage.csv").read_text() == (tmp_path / "i" / "coverage.csv").read_text()
