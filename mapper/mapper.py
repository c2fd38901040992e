"""The mapper's logic: depth in, observed surface S_t and learned prediction out."""

from __future__ import annotations

import numpy as np

from mapper.integrate import VoxelSurface, backproject
from rovergate.config import MapperConfig
from rovergate.types import (
    PREDICTED_DTYPE,
    SURFACE_DTYPE,
    MapperOutput,
    SensorFrame,
    make_cloud,
)

#: Why learned conditions cannot run yet; said at run time by every command that needs it.
NO_MODEL_REASON = ("the learned occupancy model is not shipped yet (it is issue 4's work): the "
                   "mapper publishes an empty prediction")


def has_learned_model() -> bool:
    """Whether a trained occupancy model ships with this version."""
    return False


class Mapper:
    """Integrates each depth frame into S_t and publishes the learned prediction.

    Until the occupancy model lands, the prediction is an empty cloud (never a fake one).
    """

    def __init__(self, cfg: MapperConfig) -> None:
        self.cfg = cfg
        self.surface = VoxelSurface(cfg.voxel_m)

    def step(self, frame: SensorFrame) -> MapperOutput:
        pts = backproject(frame.depth_m, frame.intrinsics, frame.T_map_camera.matrix())
        self.surface.integrate(pts)
        surface = make_cloud(self.surface.points, SURFACE_DTYPE, views=self.surface.views)
        predicted = np.zeros(0, dtype=PREDICTED_DTYPE)
        return MapperOutput(frame.step, surface, predicted)
