"""The errors library code raises. Only a command's entry point turns them into one-line
messages and exit codes (:func:`exit_code`, called by ``mission/cli.py`` and by every module
process); a program that embeds rovergate catches them by type.

Every message names the thing, says why it is wrong and how to fix it, on one line.
"""

from __future__ import annotations

import sys
from collections.abc import Callable


class RovergateError(Exception):
    """Base of every error rovergate raises on purpose (a bug raises anything else)."""


class ConfigError(RovergateError, ValueError):
    """A setting, flag or file that cannot be used as given. Found before anything starts."""


class UnknownNameError(ConfigError):
    """A name that is not among the registered choices (condition, platform, scene, start,
    planner); the message lists the valid ones."""


class CheckpointError(ConfigError):
    """The occupancy model's checkpoint is missing or unreadable (a bad file: exit code 2)."""


class TransportError(RovergateError):
    """Something awaited over the network did not come in time (a peer, a reply, the
    mission's journal)."""


class MissionFailed(RovergateError):
    """A module died more often than it may be restarted, or something the mission waited for
    did not come in time."""


class ReconfigurationFailed(RovergateError):
    """Modules restarted with a new configuration did not come up; the previous configuration
    runs on (the mission goes on)."""


def exit_code(call: Callable[[], int]) -> int:
    """Run a command's ``call`` and give its exit code: the only place a typed error becomes one
    line on stderr and a code: 2 for a setting that cannot be used (:class:`ConfigError`), 1 for
    a mission that failed (any other :class:`RovergateError`), 130 when interrupted."""
    try:
        return call()
    except ConfigError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except RovergateError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        return 130
