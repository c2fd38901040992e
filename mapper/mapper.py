"""The mapper's logic: depth in, observed surface S_t and learned prediction out."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from mapper.grid import GridSpec, OccupancyGrid
from mapper.integrate import VoxelSurface, backproject
from rovergate.conditions import get_condition
from rovergate.config import HazcamConfig, MapperConfig, MissionConfig
from rovergate.errors import ConfigError
from rovergate.geometry import hazcam_from_base
from rovergate.types import (
    PREDICTED_DTYPE,
    SURFACE_DTYPE,
    CameraIntrinsics,
    MapperOutput,
    SensorFrame,
    make_cloud,
)

if TYPE_CHECKING:  # torch is imported only by a mapper that runs the model
    from mapper.model import Checkpoint
    from mapper.predictor import OccupancyPredictor

PREDICTION_MODES = ("auto", "on", "off")


def wants_prediction(cfg: MissionConfig) -> bool:
    """Whether the mission's mapper runs the learned model (``--mapper.prediction``)."""
    mode = cfg.mapper.prediction
    if mode not in PREDICTION_MODES:
        raise ConfigError(f"--mapper.prediction {mode!r} is not a mode; choose one of: "
                          f"{', '.join(PREDICTION_MODES)}")
    if mode == "auto":
        return get_condition(cfg.condition).needs_prediction
    if mode == "off" and get_condition(cfg.condition).needs_prediction:
        raise ConfigError(f"condition {cfg.condition!r} needs the learned prediction, "
                          "but --mapper.prediction is off; use auto or on")
    return mode == "on"


def mission_checkpoint(cfg: MissionConfig) -> Checkpoint | None:
    """The model a mission's mapper runs (None: it publishes no prediction). A missing or
    corrupt checkpoint raises CheckpointError."""
    if not wants_prediction(cfg):
        return None
    from mapper.model import load_checkpoint
    return load_checkpoint(cfg.mapper.checkpoint or None)


class Mapper:
    """Integrates each depth frame into S_t and, with a checkpoint, predicts occupancy.

    With a checkpoint, each frame also goes into the occupied / free / unknown grid over the
    box of interest ``bounds_m``, the model predicts the window around the camera, and the
    published prediction is its surface at probability >= 0.5 where no return fell yet
    (:meth:`mapper.model.OccupancyPredictor.predicted`). Without one, the prediction is an
    empty cloud (never a fake one).
    """

    def __init__(self, cfg: MapperConfig, bounds_m: tuple[float, ...] | None = None,
                 checkpoint: Checkpoint | None = None, precision: str = "float32",
                 engine: str = "openvino", hazcam: HazcamConfig | None = None) -> None:
        """``precision`` and ``engine``: the model's arithmetic and runtime
        (:class:`mapper.model.OccupancyPredictor`; missions take ``MapperConfig.precision``
        and ``MapperConfig.engine``). ``hazcam``: integrate the rover's hazard cameras too
        (``--hazcam.feed-map``); None, the mast camera alone maps the scene."""
        self.cfg = cfg
        self.hazcam = hazcam
        self._hazcam_k = (None if hazcam is None else CameraIntrinsics.from_fov(
            hazcam.width_px, hazcam.height_px, hazcam.vfov_deg))
        self.surface = VoxelSurface(cfg.voxel_m)
        self.grid: OccupancyGrid | None = None
        self.predictor: OccupancyPredictor | None = None
        if checkpoint is not None:
            if bounds_m is None or not any(bounds_m):
                raise ValueError("the learned prediction needs the box of interest")
            self.grid = OccupancyGrid(GridSpec.around(bounds_m, checkpoint.window.voxel_m))
            from mapper.predictor import OccupancyPredictor
            self.predictor = OccupancyPredictor(checkpoint, self.grid, precision, engine)

    @classmethod
    def for_mission(cls, cfg: MissionConfig) -> Mapper:
        return cls(cfg.mapper, cfg.scene.bounds_m, mission_checkpoint(cfg),
                   cfg.mapper.precision, cfg.mapper.engine,
                   cfg.hazcam if cfg.hazcam.feed_map and cfg.vehicle.hazcams else None)

    def integrate(self, frame: SensorFrame) -> None:
        """Take one frame into S_t, the grid and the model's prediction, without reading the
        products out (a restarted mapper replays its past frames with this)."""
        T_cam = frame.T_map_camera.matrix()
        views = [(frame.depth_m, frame.intrinsics, T_cam)]
        if self.hazcam is not None:
            T_base = frame.T_map_base.matrix()
            views += [(depth, self._hazcam_k, hazcam_from_base(T_base, self.hazcam, name))
                      for name, depth in sorted(frame.hazcams.items()) if depth.size]
        for depth, k, T in views:
            pts = backproject(depth, k, T)
            self.surface.integrate(pts)
            if self.predictor is not None:
                self.grid.integrate(depth, k, T, returns_map=pts)
        if self.predictor is not None:
            self.predictor.update(T_cam[:3, 3])

    def step(self, frame: SensorFrame) -> MapperOutput:
        self.integrate(frame)
        surface = make_cloud(self.surface.points, SURFACE_DTYPE, views=self.surface.views)
        if self.predictor is None:
            predicted = np.zeros(0, dtype=PREDICTED_DTYPE)
        else:
            p_xyz, prob = self.predictor.predicted()
            predicted = make_cloud(p_xyz, PREDICTED_DTYPE, probability=prob)
        return MapperOutput(frame.step, surface, predicted)
