"""The operator's console (mission/link/console.py): its HTTP interface against a real ground
station, and the page itself in a real browser (Debian's chromium driven by Playwright) on a
real mission with contact windows."""

from __future__ import annotations

import http.client
import json
import logging
import os
import re
import shutil
import time
from pathlib import Path

import pytest
from conftest import LinkedMission

from mission.link.console import Console, ConsoleConfig, check_web
from mission.link.contact import ContactPlan
from mission.link.ground import GroundConfig, GroundStation, console_config
from rovergate.config import ContactConfig
from rovergate.errors import ConfigError
from rovergate.session import free_loopback_port

ROOT = Path(__file__).resolve().parents[1]
SCREENSHOT = ROOT / "docs" / "console.png"


@pytest.fixture
def station(tmp_path: Path):
    """A ground station with its console on a free loopback port, its link pointed at a port
    nothing listens on (no mission: the console answers from the station's store)."""
    cfg = GroundConfig(connect=(f"tcp/127.0.0.1:{free_loopback_port()}",), namespace="ground",
                       out=tmp_path / "g", web=True)
    s = GroundStation(cfg, logging.getLogger("test.ground"))
    queued = []
    console = Console(s, console_config(cfg), queued.append, logging.getLogger("test.console"))
    console.start()
    yield s, console, queued
    console.stop()
    s.close()


def request(console: Console, method: str, path: str, body: bytes | None = None,
            headers: dict[str, str] | None = None) -> tuple[int, dict]:
    conn = http.client.HTTPConnection("127.0.0.1", console.port, timeout=10)
    try:
        conn.request(method, path, body=body, headers={
            "Host": f"127.0.0.1:{console.port}", **(headers or {})})
        response = conn.getresponse()
        data = response.read()
        return response.status, json.loads(data) if data[:1] in (b"{", b"[") else {}
    finally:
        conn.close()


def post(console: Console, line: str, **headers: str) -> tuple[int, dict]:
    return request(console, "POST", "/api/commands", json.dumps({"line": line}).encode(),
                   {"Content-Type": "application/json", **headers})


def test_the_console_queues_what_the_allowlist_allows_and_says_why_it_refuses(station):
    s, console, queued = station
    status, answer = post(console, "pause")
    assert status == 202 and answer == {"id": 1}
    status, answer = post(console, "set gate.k=500")
    assert status == 400 and answer["error"] == "gate.k must be between 1 and 100, got '500'"
    status, answer = post(console, "set gate.k=2.5")
    assert status == 400 and "gate.k takes an integer" in answer["error"]
    status, answer = post(console, "planner cmd")
    assert status == 400 and "cannot send a command line" in answer["error"]
    status, answer = post(console, "condition nonsense")
    assert status == 400 and "unknown condition 'nonsense'" in answer["error"]
    # Only what was allowed was queued, numbered, and written to the station's record.
    assert [(c.id, c.verb) for c in queued] == [(1, "pause")]
    sent = [json.loads(line) for line in (s.cfg.out / "sent.jsonl").read_text().splitlines()]
    assert [r["line"] for r in sent] == ["pause"]
    status, state = request(console, "GET", "/api/state")
    assert status == 200 and [(c["id"], c["stage"]) for c in state["commands"]] == \
        [(1, "queued")]
    assert [c["line"] for c in state["ground_queue"]] == ["pause"]
    assert state["dictionary"]["source"] == "ground"  # no rover's list has come down
    assert {d["key"]: (d["least"], d["most"]) for d in state["dictionary"]["settings"]}[
        "gate.k"] == (1, 100)


def test_the_console_refuses_foreign_hosts_origins_and_bodies(station):
    s, console, queued = station
    # A name rebound to 127.0.0.1 by another site's page: refused.
    status, _ = request(console, "GET", "/api/state", headers={"Host": "evil.example:80"})
    assert status == 421
    status, answer = post(console, "pause", Origin="http://evil.example")
    assert status == 403 and "own page" in answer["error"]
    # A form post (not JSON), an oversized body, a body that is not a command.
    status, _ = request(console, "POST", "/api/commands", b"line=pause",
                        {"Content-Type": "application/x-www-form-urlencoded"})
    assert status == 415
    status, _ = request(console, "POST", "/api/commands", b"{" + b" " * 5000 + b"}",
                        {"Content-Type": "application/json"})
    assert status == 400
    status, _ = request(console, "POST", "/api/commands", b'{"line": 3}',
                        {"Content-Type": "application/json"})
    assert status == 400
    assert queued == [] and console.refused == 5
    # The page's own origin is let through.
    status, _ = post(console, "resume", Origin=f"http://127.0.0.1:{console.port}")
    assert status == 202


def test_beyond_loopback_the_console_needs_a_token(tmp_path: Path):
    with pytest.raises(ConfigError, match="beyond loopback.*--web-token-file"):
        check_web(ConsoleConfig(host="0.0.0.0"))
    weak = tmp_path / "weak"
    weak.write_text("short\n")
    with pytest.raises(ConfigError, match="at least 16"):
        check_web(ConsoleConfig(host="0.0.0.0", token_file=weak))
    with pytest.raises(ConfigError, match="go together"):
        check_web(ConsoleConfig(cert=tmp_path / "c.pem"))
    with pytest.raises(ConfigError, match="needs HTTPS"):
        check_web(ConsoleConfig(host="0.0.0.0", client_ca=tmp_path / "ca.pem"))


def test_a_console_with_a_token_lets_in_only_who_has_it(tmp_path: Path):
    token = "k" * 24
    (tmp_path / "token").write_text(token + "\n")
    cfg = GroundConfig(connect=(f"tcp/127.0.0.1:{free_loopback_port()}",), namespace="ground",
                       out=tmp_path / "g", web=True, web_token_file=tmp_path / "token")
    s = GroundStation(cfg, logging.getLogger("test.ground"))
    console = Console(s, console_config(cfg), lambda c: None, logging.getLogger("test.console"))
    console.start()
    try:
        status, answer = request(console, "GET", "/api/state")
        assert status == 401 and "?token=TOKEN" in answer["error"]
        assert post(console, "pause")[0] == 401
        status, _ = request(console, "GET", "/?token=" + "x" * 24)
        assert status == 401
        # The right token once: a cookie, and a redirect to the page.
        conn = http.client.HTTPConnection("127.0.0.1", console.port, timeout=10)
        conn.request("GET", f"/?token={token}")
        response = conn.getresponse()
        response.read()
        cookie = response.getheader("Set-Cookie").split(";")[0]
        assert response.status == 303 and "HttpOnly" in response.getheader("Set-Cookie")
        conn.close()
        assert request(console, "GET", "/api/state", headers={"Cookie": cookie})[0] == 200
        assert request(console, "GET", "/api/state",
                       headers={"Authorization": f"Bearer {token}"})[0] == 200
    finally:
        console.stop()
        s.close()


# --- the page in a browser ----------------------------------------------------------------------

def chromium() -> str:
    path = shutil.which("chromium") or shutil.which("chromium-browser")
    if path is None:
        pytest.fail("Debian's chromium is not installed: `make test` installs it (apt-get "
                    "install chromium), or install it yourself")
    return path


#: Chromium's flags on a machine with no network beyond the package registries.
CHROMIUM_ARGS = ["--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                 "--disable-background-networking", "--disable-component-update",
                 "--disable-sync"]


def wait_text(page, selector: str, pattern: str, timeout_s: float, what: str) -> str:
    """The text of ``selector`` once it matches ``pattern`` (the page redraws every half
    second); fails saying what it awaited."""
    deadline = time.monotonic() + timeout_s
    text = ""
    while time.monotonic() < deadline:
        text = page.locator(selector).first.inner_text()
        if re.search(pattern, text):
            return text
        page.wait_for_timeout(100)
    pytest.fail(f"the page never showed {what} in {timeout_s:.0f} s ({selector}: {text!r})")


def command_stages(page) -> list[tuple[str, str, str]]:
    rows = page.locator("#commands tbody tr")
    return [tuple(rows.nth(i).locator("td").nth(j).inner_text() for j in (0, 1, 2))
            for i in range(rows.count())]


@pytest.mark.e2e
def test_the_console_in_a_browser(tmp_path: Path):
    """A mission with windows of 3 steps every 20 and a light time of one step, its station
    serving the console; a real browser opens it. The step it shows moves only when a window
    brings telemetry, while the rover's own clock runs on; `pause` is radiated, executed and
    acknowledged, and the rover holds; `resume`; an out-of-range `set` is refused in the page
    and by the server with the rover's reason; a reload and a second browser show the same."""
    from playwright.sync_api import sync_playwright
    plan = ContactPlan(ContactConfig(period_steps=20, window_steps=3, first_window_step=2,
                                     light_time_s=60, step_s=60))
    m = LinkedMission(tmp_path, "--condition", "obs", "--contact.period-steps", "20",
                      "--contact.window-steps", "3", "--contact.first-window-step", "2",
                      "--contact.light-time-s", "60", "--contact.step-s", "60",
                      steps=600, ground_flags=("--web", "--web-port", "0"))
    try:
        url = m.ground.wait_for_line(r"console on (http://127\.0\.0\.1:\d+/)").group(1)
        with sync_playwright() as p:
            browser = p.chromium.launch(executable_path=chromium(), args=CHROMIUM_ARGS)
            page = browser.new_page(viewport={"width": 1280, "height": 1000})
            page.goto(url)
            page.wait_for_selector("body[data-ready=true]", timeout=30_000)

            # 1. The ground's step moves with the windows only, behind the rover's own.
            shown: list[tuple[int, int]] = []  # (the page's last step, the rover's step)
            deadline = time.monotonic() + 120
            while time.monotonic() < deadline and len({s for s, _ in shown}) < 4:
                text = page.locator("#last-step").inner_text()
                if text.isdigit() and m.steps:
                    shown.append((int(text), max(m.steps)))
                page.wait_for_timeout(150)
            values = sorted({s for s, _ in shown})
            assert len(values) >= 4, f"the page's step moved only through {values}"
            assert max(rover - ground for ground, rover in shown) >= 5, shown  # a blackout
            rows = [json.loads(line) for line in
                    (m.ground_out / "received.jsonl").read_text().splitlines()]
            radiated = {r["step"]: int(r["radiated_s"] // 60) for r in rows
                        if r["kind"] == "status"}
            for value in values:  # every step shown came down in a window
                assert plan.is_open(radiated[value]), (value, radiated[value])
            wait_text(page, "#plan-text", r"light time 60 s \(1 steps", 30, "the plan")

            # 2. pause: queued, radiated, executed; the rover holds.
            page.select_option("#verb", "pause")
            page.click("#send")
            wait_text(page, "#compose-result", r"command 1 queued: pause", 10, "pause queued")
            wait_text(page, "#commands tbody tr[data-id='1'] td.stage", "executed", 120,
                      "pause executed")
            wait_text(page, "#rover-state", "paused", 60, "the rover paused")
            m.watcher.waiter.wait_for(lambda: m.watcher.states.count("paused") >= 2, 60,
                                      "two 'paused' keep-alives on the rover's network")
            held = max(m.steps)
            row = page.locator("#commands tbody tr[data-id='1'] td")
            assert re.match(r"link step \d+, reaches the rover", row.nth(3).inner_text())
            assert row.nth(4).inner_text().startswith("executed at step ")

            # 3. An out-of-range set: refused in the page with the rover's reason, not sent.
            page.select_option("#verb", "set")
            page.select_option("#set-field", "gate.k")
            page.fill("#set-value", "500")
            page.click("#send")
            wait_text(page, "#compose-result",
                      re.escape("refused: gate.k must be between 1 and 100, got '500'"), 10,
                      "the refusal")
            answer = page.request.post(url + "api/commands", data={"line": "set gate.k=500"},
                                       headers={"Content-Type": "application/json"})
            assert answer.status == 400 and answer.json()["error"] == \
                "gate.k must be between 1 and 100, got '500'"
            assert max(m.steps) == held  # still paused

            # 4. resume.
            page.select_option("#verb", "resume")
            page.click("#send")
            wait_text(page, "#commands tbody tr[data-id='2'] td.stage", "executed", 120,
                      "resume executed")
            wait_text(page, "#rover-state", "running", 60, "the rover running again")
            m.wait_step(held + 3)
            wait_text(page, "#map-step", r"snapshot of step \d+", 60, "a map snapshot")
            page.wait_for_timeout(600)
            page.screenshot(path=str(tmp_path / "console.png"), full_page=True)
            if os.environ.get("ROVERGATE_SCREENSHOT"):  # the README's picture, from here
                shutil.copy(tmp_path / "console.png", SCREENSHOT)

            # 5. A reload, and a second browser, draw the same from the station's store.
            before = command_stages(page)
            assert [(i, c) for i, c, _ in before] == [("2", "resume"), ("1", "pause")]
            page.reload()
            page.wait_for_selector("body[data-ready=true]", timeout=30_000)
            assert command_stages(page) == before
            other = browser.new_context().new_page()
            other.goto(url)
            other.wait_for_selector("body[data-ready=true]", timeout=30_000)
            assert command_stages(other) == before
            browser.close()
    except BaseException:
        m.close()
        raise
    m.command("abort")
    metrics, _, _ = m.finish()
    states = [(c["verb"], c["state"]) for c in metrics["link"]["commands"]]
    assert states == [("pause", "executed"), ("resume", "executed"), ("abort", "executed")]
