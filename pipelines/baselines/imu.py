"""IMU dead reckoning: integrate the gyro (camera frame) into a rotation trajectory.

This is the drifting baseline that the offline BA (`refine`) can correct (Sec. IV-C2).
"""
from __future__ import annotations

import numpy as np

from ti_cmax import so3
from ti_cmax.errors import InputError
from ti_cmax.trajectory import Trajectory


def dead_reckoning(t: np.ndarray, gyro: np.ndarray, r0: np.ndarray | None = None,
                   gyro_bias: np.ndarray | None = None, imu_to_camera: np.ndarray | None = None) -> Trajectory:
    """Integrate gyro samples (rad/s) with the midpoint rule; R(t[0]) = r0 (identity by default).

    ``imu_to_camera`` rotates gyro vectors into the camera frame (identity unless calibration says otherwise).
    """
    t = np.asarray(t, dtype=float)
    w = np.asarray(gyro, dtype=float).reshape(-1, 3)
    if len(t) < 2:
        raise InputError(f"IMU data needs at least 2 samples, got {len(t)}")
    if gyro_bias is not None:
        w = w - np.asarray(gyro_bias, dtype=float)
    if imu_to_camera is not None:
        w = w @ np.asarray(imu_to_camera, dtype=float).T
    keep = np.concatenate([[True], np.diff(t) > 0])  # drop duplicated stamps
    return Trajectory(t[keep], so3.integrate_angular_velocity(t[keep], w[keep], r0))
