"""The platforms a mission can fly or drive, as plain data every module reads.

A platform is chosen by name (``--platform``); each module then asks the registered
:class:`Platform` what it has (a body that flies, hazard cameras, the planner ``auto`` picks)
rather than comparing names. The classes that move and check a platform are registered
beside it in their own packages, under the same name: its body in :mod:`rover_sim.sim`
(``BODIES``) and its motion model in :mod:`planner.platforms` (``MOTION_MODELS``).
"""

from __future__ import annotations

from dataclasses import dataclass

from rovergate.errors import UnknownNameError


@dataclass(frozen=True)
class Platform:
    """What the modules need to know of one platform."""

    name: str
    doc: str
    flies: bool
    """It moves in 3-D (state x, y, z, yaw, pitch) with the camera fixed to its body; else it
    drives on the terrain in SE(2) (state x, y, yaw) with the camera on a pan-tilt mast."""
    default_planner: str
    """The planner ``--planner.name auto`` runs on it."""
    hazcams: bool
    """It carries the hazard cameras (``--hazcam.enabled``)."""

    @property
    def dims(self) -> int:
        """Dimensions of its position: 3 when it flies, 2 on the ground."""
        return 3 if self.flies else 2


#: Every platform, by the name ``--platform`` takes.
PLATFORMS: dict[str, Platform] = {p.name: p for p in [
    Platform("rover", "SE(2) on the terrain, a pan-tilt mast camera, hazard cameras",
             flies=False, default_planner="greedy", hazcams=True),
    Platform("flyer", "a free-flying camera: a sphere (the paper's benchmark platform)",
             flies=True, default_planner="beam", hazcams=False),
]}


def get_platform(name: str) -> Platform:
    """The named platform; raises :class:`UnknownNameError` listing the valid ones."""
    if name not in PLATFORMS:
        raise UnknownNameError(f"unknown platform {name!r}; choose one of: "
                               f"{', '.join(PLATFORMS)} (--platform)")
    return PLATFORMS[name]
