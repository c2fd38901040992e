"""The errors library code raises. Only the command line turns them into one-line messages
and exit codes (``mission/cli.py``); a program that embeds rovergate catches them by type.

Every message names the thing, says why it is wrong and how to fix it, on one line.
"""

from __future__ import annotations


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
