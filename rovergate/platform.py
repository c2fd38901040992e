"""Platform geometry shared by the simulator and the planner: where the camera sits.

Two platforms: ``rover`` (SE(2) on the terrain; the camera on a pan-tilt mast) and ``flyer``
(a free camera; its body pose is the camera's, heading and pitch included).
"""

from __future__ import annotations

import numpy as np

from rovergate.config import SensorConfig


def rot_z(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])


def rot_y(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def rot_x(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])


#: Optical frame (x right, y down, z forward) expressed in a body frame (x fwd, y left, z up).
R_BODY_OPTICAL = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


PLATFORMS = ("rover", "flyer")


def check_platform(name: str) -> None:
    if name not in PLATFORMS:
        raise SystemExit(f"error: unknown platform {name!r}; choose one of: "
                         f"{', '.join(PLATFORMS)} (--platform)")


def camera_from_base(T_map_base: np.ndarray, sensor: SensorConfig,
                     platform: str = "rover") -> np.ndarray:
    """(4, 4) optical-frame pose of the camera for a base pose of ``platform``."""
    if platform == "flyer":
        T = T_map_base.copy()
        T[:3, :3] = T_map_base[:3, :3] @ R_BODY_OPTICAL
        return T
    T_base_mast = np.eye(4)
    T_base_mast[:3, :3] = rot_z(np.radians(sensor.pan_deg)) @ rot_y(-np.radians(sensor.tilt_deg))
    T_base_mast[:3, 3] = [sensor.mast_forward_m, 0.0, sensor.mast_height_m]
    T_mast_optical = np.eye(4)
    T_mast_optical[:3, :3] = R_BODY_OPTICAL
    return T_map_base @ T_base_mast @ T_mast_optical
