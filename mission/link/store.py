"""The ground station's store: what the ground knows of the rover, built only from what came
down the link (and what the station itself sent), never from the rover's own files.

The station's files are its memory (:class:`mission.link.ground.GroundStation` writes them;
the store reads them back when the station restarts):

- ``received.jsonl``: one row per downlinked item (status, pose, event, command_ack, map);
- ``sent.jsonl``: one row per command the station accepted (queued on the ground);
- ``uplink.jsonl``: one row per command the ground's transmitter radiated;
- ``map_latest.npy``: the newest map snapshot.

:meth:`GroundStore.state` is the picture the console's page draws (:mod:`mission.link.console`):
every browser and every reload gets the same, because it is computed here. Time on the ground
is mission time: the simulated seconds of the link's clock, which the ground estimates from
the frames it received (a frame radiated at ``radiated_s`` arrives one light time later) and
the transmitter's reports, advanced at the wall-clock rate those samples show.
"""

from __future__ import annotations

import contextlib
import json
import math
import threading
import time
from pathlib import Path
from statistics import median
from typing import Any

import numpy as np

from mission.link.bridge import ONBOARD_QUEUE_EVENT
from mission.link.commands import DICTIONARY_EVENT, Dictionary
from mission.link.contact import CONTACT_PLAN_EVENT
from mission.scoring.evaluation import stuck_flags

#: Events that describe the link rather than the mission (drawn in their own panels).
LINK_EVENTS = (CONTACT_PLAN_EVENT, DICTIONARY_EVENT, ONBOARD_QUEUE_EVENT)
#: Most events, and most map points, the page is sent.
MAX_EVENTS = 300
MAX_MAP_POINTS = 8000
#: Clock samples kept for the wall-clock rate of mission time.
CLOCK_SAMPLES = 40
FINAL_STATES = ("done", "aborted")


def read_jsonl(path: Path) -> list[dict[str, Any]]:
    """The rows of a JSON-lines file (none if it does not exist); a torn last line (the
    station was killed while writing it) is left out."""
    if not path.exists():
        return []
    rows = []
    for line in path.read_text().splitlines():
        try:
            rows.append(json.loads(line))
        except ValueError:
            continue
    return rows


class GroundStore:
    """The ground's picture of the mission, updated as rows come in; thread-safe."""

    def __init__(self, out: Path, dictionary: Dictionary) -> None:
        self.out = Path(out)
        self._lock = threading.Lock()
        self.dictionary = dictionary
        self.plan: dict[str, Any] | None = None
        self.onboard: dict[str, Any] | None = None
        self.statuses: dict[int, dict[str, Any]] = {}
        self.last_status: dict[str, Any] | None = None
        self.poses: dict[int, list[float]] = {}
        self.events: list[dict[str, Any]] = []
        self.commands: dict[int, dict[str, Any]] = {}
        self.paused = False
        self.final: str | None = None
        self.map_step: int | None = None
        self._map_cache: tuple[float, dict[str, Any]] | None = None
        self._clock: list[tuple[float, float]] = []  # (mission seconds at the ground, wall)
        self.received = 0
        self.rover_on_link = False
        self.rover_left = False
        for row in read_jsonl(self.out / "sent.jsonl"):
            self.add_sent(row)
        for row in read_jsonl(self.out / "received.jsonl"):
            self.add_received(row)
        for row in read_jsonl(self.out / "uplink.jsonl"):
            self.add_radiated(row)

    # --- rows in ----------------------------------------------------------------------------

    def add_received(self, row: dict[str, Any]) -> None:
        """One row of received.jsonl."""
        with self._lock:
            self.received += 1
            if "error" in row:
                return
            if self.plan is not None and "radiated_s" in row:
                arrived = row["radiated_s"] + self.plan["light_steps"] * self.plan["step_s"]
                self._tick(arrived, row["received_wall"])
            kind = row["kind"]
            if kind == "status":
                self.statuses[int(row["step"])] = row
                if self.last_status is None or row["step"] >= self.last_status["step"]:
                    self.last_status = row
                if row.get("state") in FINAL_STATES:
                    self.final = row["state"]
            elif kind == "pose":
                self.poses[int(row["step"])] = row["position"]
            elif kind == "map":
                self.map_step = int(row["step"])
            elif kind == "event":
                self._event(row)
            elif kind == "command_ack":
                c = self._command(int(row["id"]), row.get("verb", ""))
                c["ack"] = {"state": row["state"], "step": row["executed_step"],
                            "received_s": row["received_s"], "detail": row.get("detail", ""),
                            "radiated_s": row["radiated_s"]}
                c["stage"] = row["state"]
                if c.get("radiated") is None and self.plan is not None:
                    # The transmitter's report was lost (the station was down): the ack says
                    # when it reached the rover, one light time after it was radiated.
                    c["radiated"] = {"step": round(row["received_s"] / self.plan["step_s"])
                                     - self.plan["light_steps"], "from": "ack"}

    def _event(self, row: dict[str, Any]) -> None:
        kind, detail = row["event"], row.get("detail", "")
        if kind in LINK_EVENTS:  # drawn in their own panels; a malformed one is skipped
            with contextlib.suppress(ValueError, KeyError, TypeError):
                if kind == CONTACT_PLAN_EVENT:
                    self.plan = json.loads(detail)
                elif kind == DICTIONARY_EVENT:
                    self.dictionary = Dictionary.from_json(detail, "rover")
                else:
                    self.onboard = {**json.loads(detail),
                                    "received_wall": row["received_wall"]}
            return
        if kind == "paused":
            self.paused = True
        elif kind == "resumed":
            self.paused = False
        elif kind.startswith("mission-") and kind[8:] in FINAL_STATES:
            self.final = kind[8:]
        self.events.append({"step": row["step"], "kind": kind, "detail": detail,
                            "received_wall": row["received_wall"]})
        del self.events[:-MAX_EVENTS]

    def add_sent(self, row: dict[str, Any]) -> None:
        """One row of sent.jsonl: a command accepted on the ground."""
        with self._lock:
            c = self._command(int(row["id"]), row["verb"])
            c.update(args=row.get("args", []), line=row.get("line") or " ".join(
                [row["verb"], *row.get("args", [])]), queued_wall=row.get("sent_wall"))
            if c["stage"] is None:
                c["stage"] = "queued"

    def add_radiated(self, row: dict[str, Any]) -> None:
        """One row of uplink.jsonl: the ground's transmitter radiated a command."""
        with self._lock:
            if self.plan is not None:
                self._tick(row["step"] * self.plan["step_s"], row["wall"])
            c = self._command(int(row["id"]), row.get("verb", ""))
            c["radiated"] = {"step": row["step"], "arrives_s": row["arrives_s"],
                             "wall": row["wall"], "from": "transmitter"}
            if c.get("stage") in (None, "queued"):
                c["stage"] = "radiated"

    def _command(self, command_id: int, verb: str) -> dict[str, Any]:
        if command_id not in self.commands:
            self.commands[command_id] = {"id": command_id, "verb": verb, "args": [],
                                         "line": verb, "stage": None, "radiated": None,
                                         "ack": None, "queued_wall": None}
        return self.commands[command_id]

    def _tick(self, mission_s: float, wall: float) -> None:
        self._clock.append((mission_s, wall))
        del self._clock[:-CLOCK_SAMPLES]

    # --- the picture ------------------------------------------------------------------------

    def _wall_per_mission_s(self) -> float | None:
        rates = []
        samples = sorted(self._clock, key=lambda sample: sample[1])
        for (s0, w0), (s1, w1) in zip(samples, samples[1:], strict=False):
            if s1 > s0 and w1 >= w0:
                rates.append((w1 - w0) / (s1 - s0))
        return median(rates) if rates else None

    def mission_now_s(self, now_wall: float) -> float | None:
        """The ground's estimate of the link's clock now, in mission seconds (None before
        the contact plan came down)."""
        if self.plan is None or not self._clock:
            return None
        s, w = max(self._clock)
        rate = self._wall_per_mission_s()
        if rate is None or rate <= 0 or self.final is not None or self.rover_left:
            return s
        return s + max(0.0, now_wall - w) / rate

    def state(self, now_wall: float | None = None) -> dict[str, Any]:
        """Everything the page draws, as JSON-ready values."""
        now_wall = time.time() if now_wall is None else now_wall
        with self._lock:
            return self._state(now_wall)

    def _state(self, now_wall: float) -> dict[str, Any]:
        plan = self.plan
        now_s = self.mission_now_s(now_wall)
        step_s = plan["step_s"] if plan else None
        now_link = math.floor(now_s / step_s) if now_s is not None and step_s else None
        last = self.last_status
        rover: dict[str, Any] = {"state": self._rover_state(), "last_step": None,
                                 "steps_total": None, "age_s": None, "predicted_step": None,
                                 "on_link": self.rover_on_link}
        if last is not None:
            rover.update(last_step=last["step"], steps_total=self._steps_total(),
                         condition=last.get("condition"), coverage=last.get("coverage"),
                         radiated_s=last["radiated_s"])
            if now_s is not None:
                rover["age_s"] = max(0.0, now_s - last["radiated_s"])
                predicted = last["step"]
                if rover["state"] == "running" and step_s:
                    predicted += max(0, math.floor((now_s - last["radiated_s"]) / step_s))
                total = self._steps_total()
                rover["predicted_step"] = min(predicted, total) if total else predicted
        windows = plan["windows"] if plan else []
        timeline = None
        if plan is not None:
            upcoming = [w for w in windows if now_link is None or w[1] > now_link]
            timeline = {**plan, "now_s": now_s, "now_link_step": now_link,
                        "in_window": bool(now_link is not None and upcoming
                                          and upcoming[0][0] <= now_link),
                        "next_window": upcoming[0] if upcoming else None}
        steps = sorted(self.poses)
        positions = np.array([self.poses[t] for t in steps], dtype=np.float64).reshape(-1, 3)
        metres = float(np.linalg.norm(np.diff(positions, axis=0), axis=1).sum()) \
            if len(positions) > 1 else 0.0
        stuck = int(stuck_flags(positions).sum()) if len(positions) else 0
        commands = sorted(self.commands.values(), key=lambda c: c["id"])
        return {
            "rover": rover,
            "plan": timeline,
            "onboard_queue": self.onboard,
            "ground_queue": [c for c in commands if c["stage"] == "queued"],
            "telemetry": {
                "coverage": [[t, self.statuses[t]["coverage"]] for t in sorted(self.statuses)],
                "collisions": last.get("collisions", 0) if last else 0,
                "metres_driven": metres, "stuck_steps": stuck, "poses": len(steps),
                "path": positions[:, :2].round(3).tolist(),
                "events": self.events[-MAX_EVENTS:],
                "map_step": self.map_step,
                "received": self.received,
            },
            "commands": commands,
            "dictionary": {**json.loads(self.dictionary.to_json()),
                           "source": self.dictionary.source},
            "now_wall": now_wall,
        }

    def _steps_total(self) -> int | None:
        return self.last_status.get("steps_total") if self.last_status else None

    def _rover_state(self) -> str:
        if self.final is not None:
            return self.final
        if self.last_status is None:
            return "unknown" if not self.rover_left else "failed"
        if self.rover_left:
            return "failed"  # the mission manager left the link before a final status
        return "paused" if self.paused else "running"

    def map_snapshot(self) -> dict[str, Any]:
        """The newest map snapshot seen from above: x, y, z of at most
        :data:`MAX_MAP_POINTS` points (thinned evenly), and the path driven."""
        path = self.out / "map_latest.npy"
        try:
            mtime = path.stat().st_mtime
        except FileNotFoundError:
            return {"step": None, "points": [], "path": []}
        if self._map_cache is None or self._map_cache[0] != mtime:
            try:
                cloud = np.load(path)
            except (OSError, ValueError):
                return {"step": None, "points": [], "path": []}
            if len(cloud) > MAX_MAP_POINTS:
                cloud = cloud[np.linspace(0, len(cloud) - 1, MAX_MAP_POINTS).astype(np.int64)]
            xyz = np.c_[cloud["x"], cloud["y"], cloud["z"]].astype(np.float64).round(2)
            self._map_cache = (mtime, {"step": self.map_step, "points": xyz.tolist()})
        with self._lock:
            steps = sorted(self.poses)
            path_xy = [self.poses[t][:2] for t in steps]
        return {**self._map_cache[1], "path": path_xy}
