"""The contact plan: when the rover can talk to Earth, how late, and how fast.

Time on the link is simulated: step t of the mission clock is at ``t * step_s`` simulated
seconds, and the bridge acts once per step (at the step boundary), so every delay is rounded
up to whole steps. A window ``[start, start + duration)`` (in steps) is when the link is up.
Anything is *radiated* only inside a window, by either end, and *received* one light time
later, window or not (a signal already on its way arrives). The downlink radiates at most
``downlink_kbps`` per simulated second; budget left over at one step carries to the next step
of the same window, not beyond it.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from typing import Any

from rovergate.config import ContactConfig

CONTACT_PLAN_EVENT = "contact-plan"
"""The kind of the event the rover downlinks at the start of a mission: the plan as JSON
(:meth:`ContactPlan.describe`), for the ground's timeline."""


class ContactPlanError(ValueError):
    """A contact plan that cannot be used (the message says how to fix it)."""


@dataclass
class ContactPlan:
    """Windows, light time and rate of one mission (derived from :class:`ContactConfig`)."""

    cfg: ContactConfig
    _explicit: list[tuple[int, int]] = field(default_factory=list)
    _held_from: int | None = None

    def __post_init__(self) -> None:
        c = self.cfg
        for spec in c.windows:
            m = re.fullmatch(r"\s*(\d+)\s*\+\s*(\d+)\s*", spec)
            if not m or int(m.group(2)) < 1:
                raise ContactPlanError(
                    f"contact window {spec!r} is not START+DURATION in steps; write e.g. "
                    "--contact.windows 10+5 40+3")
            self._explicit.append((int(m.group(1)), int(m.group(2))))
        if not self._explicit and (c.window_steps < 1 or c.period_steps < c.window_steps):
            raise ContactPlanError(
                f"contact plan needs 1 <= --contact.window-steps <= --contact.period-steps, "
                f"got {c.window_steps} and {c.period_steps}")
        if c.step_s <= 0 or c.light_time_s < 0 or c.downlink_kbps <= 0:
            raise ContactPlanError("contact plan needs --contact.step-s > 0, "
                                   "--contact.light-time-s >= 0 and --contact.downlink-kbps > 0")

    def hold_open(self, step: int) -> None:
        """Keep the link up from ``step`` on: after the mission, once the plan has no window
        left (:meth:`end_of_mission`)."""
        self._held_from = step if self._held_from is None else min(self._held_from, step)

    def end_of_mission(self, steps: int, drain_steps: int) -> str:
        """How the telemetry left after the last step reaches the ground, in words; raises
        :class:`ContactPlanError` if it never could.

        After the last step the clock runs on in idle steps (at most ``drain_steps``, with a
        ground station on the link) and the plan's windows go on; once the plan has no window
        left (an explicit plan after its last window), the link is held open until everything
        is acknowledged. A periodic plan whose next window after the mission opens too late
        for the round trip within ``drain_steps`` is refused."""
        round_trip = 2 * self.light_steps + 2
        first = self.next_open(steps + 1)
        if first is None:
            if round_trip > drain_steps:
                raise ContactPlanError(
                    f"the end of the mission could never reach the ground: a round trip takes "
                    f"{round_trip} steps, more than --contact.drain-steps {drain_steps}; raise "
                    "--contact.drain-steps")
            return (f"after the last step the link is held open (the plan has no window "
                    f"left) for up to {drain_steps} idle steps until everything is "
                    "acknowledged")
        # A pause lets the clock run on past the last step: take the worst wait for a
        # window, not the one after step ``steps``.
        wait = first - steps if self._explicit else max(
            first - steps, self.cfg.period_steps - self.cfg.window_steps + 1)
        needed = wait + round_trip
        if needed > drain_steps:
            raise ContactPlanError(
                f"the end of the mission could never reach the ground: after the last step a "
                f"window can be {wait} steps away (the first after step {steps} opens at "
                f"{first}), and with the round trip that needs {needed} idle steps, more than "
                f"--contact.drain-steps {drain_steps}; raise --contact.drain-steps, or plan "
                "windows nearer the end")
        return (f"after the last step the windows go on (the next at step {first}), for up "
                f"to {drain_steps} idle steps until everything is acknowledged"
                + (", and the link is held open after the plan's last window"
                   if self._explicit else ""))

    def is_open(self, step: int) -> bool:
        """Whether the link is up during step ``step``."""
        if self._held_from is not None and step >= self._held_from:
            return True
        if self._explicit:
            return any(s <= step < s + d for s, d in self._explicit)
        c = self.cfg
        return step >= c.first_window_step and \
            (step - c.first_window_step) % c.period_steps < c.window_steps

    def next_open(self, step: int) -> int | None:
        """The first step >= ``step`` with the link up (None: no window ever again)."""
        planned = self._next_planned(step)
        if self._held_from is None:
            return planned
        held = max(step, self._held_from)
        return held if planned is None else min(planned, held)

    def _next_planned(self, step: int) -> int | None:
        if self._explicit:
            later = [max(s, step) for s, d in self._explicit if s + d > step]
            return min(later) if later else None
        c = self.cfg
        if step < c.first_window_step:
            return c.first_window_step
        phase = (step - c.first_window_step) % c.period_steps
        return step if phase < c.window_steps else step + c.period_steps - phase

    @property
    def light_steps(self) -> int:
        """Steps a signal takes to arrive (the light time, rounded up to whole steps)."""
        return math.ceil(self.cfg.light_time_s / self.cfg.step_s - 1e-9)

    @property
    def bytes_per_step(self) -> int:
        """What the downlink radiates in one step of an open window."""
        return int(self.cfg.downlink_kbps * 1000 / 8 * self.cfg.step_s)

    def describe(self, last_step: int) -> dict[str, Any]:
        """The plan as the ground's console draws it: timing, rate, and every window up to
        ``last_step`` as [start, end exclusive] in link steps."""
        c = self.cfg
        return {"step_s": c.step_s, "light_time_s": c.light_time_s,
                "light_steps": self.light_steps, "downlink_kbps": c.downlink_kbps,
                "bytes_per_step": self.bytes_per_step,
                "windows": [list(w) for w in self.windows_between(0, last_step)]}

    def windows_between(self, first: int, last: int) -> list[tuple[int, int]]:
        """The windows overlapping steps ``first..last``, as (start, end exclusive)."""
        out: list[tuple[int, int]] = []
        t = first
        while t <= last:
            nxt = self.next_open(t)
            if nxt is None or nxt > last:
                break
            end = nxt
            while end <= last and self.is_open(end):
                end += 1
            out.append((nxt, end))
            t = end
        return out
