"""Partial observations for training and evaluating the occupancy model, from the simulator.

A *walk* is a seeded sequence of camera poses through a scene: the rover driving between
traversable poses with its mast panned and tilted, or the flyer at varied heights and pitches.
Each pose is rendered by the same pybullet renderer and degraded by the same sensing model as
a mission, so the model trains on exactly what the mapper will see.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, replace

import numpy as np

from rover_sim.catalog import start_candidates
from rover_sim.flyer import FlyerBody
from rover_sim.rover import RoverBody
from rover_sim.scene import Scene
from rover_sim.sensing import Sensing
from rover_sim.world import PyBulletWorld
from rovergate.config import RoverConfig, SensingConfig, SensorConfig
from rovergate.geometry import camera_from_base
from rovergate.platforms import get_platform
from rovergate.types import CameraIntrinsics


@dataclass
class WalkFrame:
    """One rendered pose of a walk."""

    step: int
    depth_m: np.ndarray
    """(H, W) float32 z-depth, degraded as configured, NaN where there is no return."""
    intrinsics: CameraIntrinsics
    T_map_camera: np.ndarray
    """(4, 4) true camera pose (walks have no pose drift)."""


def random_sensing(rng: np.random.Generator) -> SensingConfig:
    """Mild depth degradations, drawn per walk, so that the model has seen noise and holes."""
    return SensingConfig(noise_frac=float(rng.uniform(0.0, 0.01)),
                         dropout_pixel_prob=float(rng.uniform(0.0, 0.1)),
                         dropout_blob_frac=float(rng.uniform(0.0, 0.15)))


def walk(scene: Scene, platform: str, steps: int, seed: int,
         sensing: SensingConfig | None = None,
         sensor: SensorConfig | None = None) -> Iterator[WalkFrame]:
    """``steps`` + 1 frames of a seeded walk of ``platform`` through ``scene``.

    Poses are drawn from the 1 m grid of poses where both platforms fit (the rule that picks
    scene starts): each step turns by up to about 45 degrees and moves 1 to 3.5 m to the
    nearest fitting pose. The rover's mast pans +-40 degrees and tilts -35 to -5 degrees; the
    flyer flies 0.8 to 5 m above the ground and pitches -50 to 0 degrees.
    """
    rng = np.random.default_rng(seed)
    sensor = sensor or SensorConfig()
    xs, ys, ok = start_candidates(scene)
    rows, cols = np.nonzero(ok)
    if len(rows) == 0:
        return
    cells = np.c_[xs[cols], ys[rows]]
    flying = get_platform(platform).flies
    rover = None if flying else RoverBody(scene, RoverConfig())
    world = PyBulletWorld(scene, sensor, None if flying else RoverConfig())
    degrade = Sensing(sensing or SensingConfig(), seed)
    try:
        pos = cells[rng.integers(len(cells))]
        heading = float(rng.uniform(-np.pi, np.pi))
        for step in range(steps + 1):
            if step > 0:
                for _ in range(12):
                    h = heading + rng.normal(0.0, np.radians(45))
                    target = pos + rng.uniform(1.0, 3.5) * np.array([np.cos(h), np.sin(h)])
                    d = np.linalg.norm(cells - target, axis=1)
                    k = int(np.argmin(d))
                    if d[k] < 1.5 and np.linalg.norm(cells[k] - pos) > 0.5:
                        pos, heading = cells[k], float(h)
                        break
                else:
                    heading = float(rng.uniform(-np.pi, np.pi))
            x, y = (float(v) for v in pos)
            if flying:
                z = float(scene.height_at(x, y)) + rng.uniform(0.8, 5.0)
                pitch = np.radians(rng.uniform(-50.0, 0.0))
                yaw = heading + rng.normal(0.0, np.radians(30))
                T_base = FlyerBody.base_pose(x, y, z, yaw, pitch)
                T_cam = camera_from_base(T_base, sensor, "flyer")
            else:
                T_base = rover.base_pose(x, y, heading)
                mast = replace(sensor, pan_deg=float(rng.uniform(-40, 40)),
                               tilt_deg=float(rng.uniform(-35, -5)))
                T_cam = camera_from_base(T_base, mast, "rover")
            world.set_rover_pose(T_base)
            depth = degrade.degrade(world.render_depth(T_cam), world.intrinsics, step)
            yield WalkFrame(step, depth, world.intrinsics, T_cam)
    finally:
        world.close()
