"""Synthetic IMU for a purely rotating camera (IMU frame = camera frame).

gyro = omega(t) (camera frame) + constant seeded bias + white noise;
acc  = specific force of a static point, R(t)^T (-g_world) + white noise, with gravity along the
world +y axis (y points down, CONVENTIONS.md), so a level camera reads (0, -9.81, 0).
"""
from __future__ import annotations

import numpy as np

from .trajectories import RotationalMotion, sample_times


def simulate_imu(motion: RotationalMotion, rate: float, *, gyro_bias_std: float, gyro_noise_std: float,
                 acc_noise_std: float, gravity: float = 9.81, seed: int = 0):
    """Return (t, acc (N,3), gyro (N,3), gyro_bias (3,)) sampled at ``rate`` Hz."""
    rng = np.random.default_rng([seed, 23])
    bias = rng.normal(0.0, gyro_bias_std, 3)
    t = sample_times(motion.duration, rate)
    gyro = motion.omega(t) + bias + rng.normal(0.0, gyro_noise_std, (len(t), 3))
    g_world = np.array([0.0, gravity, 0.0])
    r = motion.rotation(t)
    acc = np.einsum("nji,j->ni", r, -g_world) + rng.normal(0.0, acc_noise_std, (len(t), 3))
    return t, acc, gyro, bias
