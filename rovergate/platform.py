"""Rover platform geometry shared by the simulator and the planner: the mast camera."""

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


def camera_from_base(T_map_base: np.ndarray, sensor: SensorConfig) -> np.ndarray:
    """(4, 4) optical-frame pose of the mast camera for a rover base pose."""
    T_base_mast = np.eye(4)
    T_base_mast[:3, :3] = rot_z(np.radians(sensor.pan_deg)) @ rot_y(-np.radians(sensor.tilt_deg))
    T_base_mast[:3, 3] = [sensor.mast_forward_m, 0.0, sensor.mast_height_m]
    T_mast_optical = np.eye(4)
    T_mast_optical[:3, :3] = R_BODY_OPTICAL
    return T_map_base @ T_base_mast @ T_mast_optical
