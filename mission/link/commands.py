"""The ground commands and the one allowlist that the console's page, the ground station and
the rover all check.

A command is a verb and its arguments (:class:`rovergate.types.GroundCommand`)::

    pause | resume | abort
    set gate.k=3 [planner.n_candidates=16 ...]     (fields of IN_FLIGHT, within their ranges)
    condition gated                                (a condition the rover knows)
    planner beam                                   (a planner the rover knows, or a program
                                                    its launch named: never a command line)

The checks live here once. :func:`parse_command` reads a typed line; :func:`check_command`
holds it against a :class:`Dictionary` (what may be sent: every settable field with its kind
and range, the conditions and the planners). The rover downlinks its own dictionary at the
start of a mission (an event of kind :data:`DICTIONARY_EVENT`): the station and the page use
it from then on, and before it comes down they use the one of the ground's own installation
(:func:`local_dictionary`), which has the same fields and ranges. The rover checks every
command again as it executes it (:func:`mission.link.operations.apply_settings`, through
:func:`setting_value`), against its configuration as it stands.
"""

from __future__ import annotations

import dataclasses
import json
import re
import shlex
from dataclasses import dataclass
from typing import Any

from rovergate.types import GroundCommand

VERBS = ("pause", "resume", "abort", "set", "condition", "planner")

#: What ``set`` may change in flight: ``section.field`` -> (least, most). Nothing else can be
#: set from the ground (not a planner's command line, not a safety margin, not the sensor);
#: a value of another type, out of range, NaN or infinite is refused. The modules built from
#: the section restart (:func:`rovergate.graph.readers`).
IN_FLIGHT: dict[str, tuple[float, float]] = {
    "gate.k": (1, 100),
    "gate.epsilon_frac": (0.001, 0.5),
    "gate.view_tolerance_m": (0.01, 5.0),
    "planner.n_candidates": (1, 256),
    "planner.beam_width": (1, 16),
    "planner.beam_depth": (1, 6),
    "planner.beam_branch": (1, 64),
    "planner.max_step_m": (0.1, 10.0),
    "planner.max_attempts": (1, 64),
    "planner.observed_min_views": (1, 50),
    "planner.gain_voxel_m": (0.05, 2.0),
}

DICTIONARY_EVENT = "command-dictionary"
"""The kind of the event whose detail is the rover's :class:`Dictionary` as JSON."""

#: What ``set`` reads as a value: a plain decimal number, short (json.loads then cannot
#: overflow, recurse or take long), or NaN and the infinities (refused by the range check).
_NUMBER = re.compile(r"-?\d{1,12}(\.\d{1,12})?([eE][-+]?\d{1,3})?|NaN|-?Infinity")


class CommandError(ValueError):
    """A command that is refused (on the ground before it is sent, or by the rover: its
    acknowledgement says why)."""


@dataclass(frozen=True)
class Setting:
    """One field ``set`` may change."""

    key: str
    kind: str
    """``integer`` or ``number``."""
    least: float
    most: float


@dataclass(frozen=True)
class Dictionary:
    """What may be sent: the settable fields, the conditions, the planners."""

    settings: tuple[Setting, ...]
    conditions: tuple[str, ...]
    planners: tuple[str, ...]
    source: str = "ground"
    """``rover`` (downlinked), ``mission`` (made from the mission's configuration) or
    ``ground`` (this installation's, until the rover's comes)."""

    def setting(self, key: str) -> Setting:
        for s in self.settings:
            if s.key == key:
                return s
        raise CommandError(f"cannot set {key!r} in flight; settable: "
                           + ", ".join(s.key for s in self.settings))

    def to_json(self) -> str:
        return json.dumps({"settings": [dataclasses.asdict(s) for s in self.settings],
                           "conditions": list(self.conditions),
                           "planners": list(self.planners)}, separators=(",", ":"))

    @classmethod
    def from_json(cls, text: str, source: str = "rover") -> Dictionary:
        """The dictionary of a downlinked event; ValueError if it is not one."""
        data = json.loads(text)
        settings = tuple(Setting(str(s["key"]), str(s["kind"]), float(s["least"]),
                                 float(s["most"])) for s in data["settings"])
        if not all(s.kind in ("integer", "number") for s in settings):
            raise ValueError("a setting's kind is integer or number")
        return cls(settings, tuple(map(str, data["conditions"])),
                   tuple(map(str, data["planners"])), source)


def setting_kinds() -> dict[str, str]:
    """``integer`` or ``number`` for every field of :data:`IN_FLIGHT` (its type in
    :class:`rovergate.config.MissionConfig`)."""
    from rovergate.config import MissionConfig
    cfg = MissionConfig()
    out = {}
    for key in IN_FLIGHT:
        section, _, name = key.partition(".")
        value = getattr(getattr(cfg, section), name)
        out[key] = "integer" if isinstance(value, int) else "number"
    return out


def local_dictionary(planner_programs: tuple[str, ...] = (), source: str = "ground"
                     ) -> Dictionary:
    """This installation's dictionary: :data:`IN_FLIGHT`, its conditions and built-in (and
    registered) planners, and ``planner_programs`` (the names a launch gave
    ``--planner.programs``). ``source``: ``rover`` or ``mission`` when the programs are the
    mission's own (a planner name outside the list is refused), ``ground`` when they are not
    known (one is left for the rover to decide)."""
    from planner.planner import planner_names
    from rovergate.conditions import condition_names
    kinds = setting_kinds()
    return Dictionary(tuple(Setting(k, kinds[k], float(lo), float(hi))
                            for k, (lo, hi) in IN_FLIGHT.items()),
                      tuple(condition_names()),
                      ("auto", *planner_names(), *planner_programs), source)


def setting_value(setting: Setting, raw: str) -> int | float:
    """The value of ``set KEY=raw`` for ``setting``; CommandError says why it is refused."""
    raw = raw.strip()
    # Parsed only if it is a short plain number: no huge or nested literal reaches json.
    value: Any = json.loads(raw) if _NUMBER.fullmatch(raw) else None
    if setting.kind == "number" and isinstance(value, int) and not isinstance(value, bool):
        value = float(value)
    wanted = int if setting.kind == "integer" else float
    if type(value) is not wanted:
        kind = "an integer" if setting.kind == "integer" else "a number"
        raise CommandError(f"{setting.key} takes {kind}, got {raw[:40]!r}")
    least, most = setting.least, setting.most
    if not least <= value <= most:  # NaN fails too
        raise CommandError(f"{setting.key} must be between {_plain(least)} and "
                           f"{_plain(most)}, got {raw!r}")
    return value  # type: ignore[no-any-return]


def _plain(x: float) -> str:
    return str(int(x)) if float(x).is_integer() else repr(float(x))


def parse_command(line: str, command_id: int) -> GroundCommand:
    """A typed command line -> :class:`GroundCommand` (its form only); CommandError says
    what is wrong."""
    try:
        words = shlex.split(line)
    except ValueError as exc:
        raise CommandError(f"cannot read {line.strip()!r}: {exc}") from None
    if not words or words[0] not in VERBS:
        raise CommandError(f"unknown command {line.strip()!r}; one of: {', '.join(VERBS)}")
    verb, args = words[0], words[1:]
    if verb in ("pause", "resume", "abort") and args:
        raise CommandError(f"{verb} takes no arguments")
    if verb == "set" and (not args or not all("=" in a for a in args)):
        raise CommandError("set takes section.field=value pairs, e.g. set gate.k=3")
    if verb in ("condition", "planner") and len(args) != 1:
        raise CommandError(f"{verb} takes one name, e.g. {verb} "
                           f"{'gated' if verb == 'condition' else 'frontier'}"
                           + ("" if verb == "condition" else
                              " (a built-in planner or one the mission was launched with)"))
    return GroundCommand(command_id, verb, args)


def check_command(command: GroundCommand, dictionary: Dictionary) -> None:
    """CommandError if ``dictionary`` does not allow ``command`` (what, and why)."""
    if command.verb == "set":
        for pair in command.args:
            key, _, raw = pair.partition("=")
            setting_value(dictionary.setting(key.strip()), raw)
    elif command.verb == "condition" and command.args[0] not in dictionary.conditions:
        raise CommandError(f"unknown condition {command.args[0]!r}; choose one of: "
                           + ", ".join(dictionary.conditions))
    elif command.verb == "planner" and command.args[0] not in dictionary.planners and \
            (dictionary.source != "ground" or command.args[0] == "cmd"):
        # Until the rover's list comes down, a name this installation does not know may be a
        # program the mission's launch named (--planner.programs): the rover decides.
        why = ("the ground cannot send a command line; " if command.args[0] == "cmd" else
               f"unknown planner {command.args[0]!r}; ")
        raise CommandError(why + "choose one of: " + ", ".join(dictionary.planners)
                           + " (programs are fixed at launch: --planner.programs NAME=COMMAND)")


def read_command(line: str, command_id: int, dictionary: Dictionary) -> GroundCommand:
    """:func:`parse_command` and :func:`check_command` in one."""
    command = parse_command(line, command_id)
    check_command(command, dictionary)
    return command


def command_line(command: GroundCommand) -> str:
    """The command as it would be typed."""
    return " ".join([command.verb, *(shlex.quote(a) for a in command.args)])
