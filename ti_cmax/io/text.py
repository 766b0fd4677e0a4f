"""Small whitespace-separated text tables: TUM trajectories, ECD imu.txt, angular velocity.

All files accept '#' comments and blank lines; a malformed line raises InputError naming file and line.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .. import so3
from ..errors import InputError
from ..trajectory import Trajectory


@dataclass(frozen=True, eq=False)
class ImuData:
    """IMU samples: t (N,) seconds, acc (N, 3) m/s^2, gyro (N, 3) rad/s (sensor frame as stored)."""

    t: np.ndarray
    acc: np.ndarray
    gyro: np.ndarray

    def __post_init__(self):
        t = np.ascontiguousarray(self.t, dtype=np.float64).reshape(-1)
        acc = np.ascontiguousarray(self.acc, dtype=np.float64).reshape(-1, 3)
        gyro = np.ascontiguousarray(self.gyro, dtype=np.float64).reshape(-1, 3)
        if not (len(t) == len(acc) == len(gyro)):
            raise InputError(f"IMU data has {len(t)} timestamps, {len(acc)} accelerations, {len(gyro)} gyro rows")
        object.__setattr__(self, "t", t)
        object.__setattr__(self, "acc", acc)
        object.__setattr__(self, "gyro", gyro)

    def __len__(self) -> int:
        return len(self.t)

    def slice_time(self, t_start: float, t_end: float) -> "ImuData":
        keep = (self.t >= t_start) & (self.t < t_end)
        return ImuData(self.t[keep], self.acc[keep], self.gyro[keep])


def read_table(path, ncols: int, expected: str, min_rows: int = 1) -> np.ndarray:
    """Read a numeric table with exactly ``ncols`` columns per data line, (N, ncols) float64."""
    path = Path(path)
    source = str(path)
    if not path.is_file():
        raise InputError("file not found", source=source)
    rows = []
    with open(path, "r", encoding="utf-8", errors="replace") as f:
        for lineno, raw in enumerate(f, 1):
            k = raw.find("#")
            if k >= 0:
                raw = raw[:k]
            parts = raw.replace(",", " ").split()
            if not parts:
                continue
            if len(parts) != ncols:
                raise InputError(f"expected {ncols} values '{expected}', got {len(parts)}", source=source, line=lineno)
            try:
                vals = [float(v) for v in parts]
            except ValueError:
                raise InputError(f"expected numbers '{expected}', got {raw.strip()[:80]!r}",
                                 source=source, line=lineno) from None
            if not all(np.isfinite(vals)):
                raise InputError(f"non-finite value in {raw.strip()[:80]!r}", source=source, line=lineno)
            rows.append(vals)
    if len(rows) < min_rows:
        raise InputError(f"the file holds no data (expected lines '{expected}')", source=source)
    return np.asarray(rows, dtype=np.float64).reshape(-1, ncols)


def _sorted_times(t: np.ndarray, source: str, strict: bool):
    d = np.diff(t)
    bad = (d <= 0) if strict else (d < 0)
    if bad.any():
        i = int(np.argmax(bad)) + 1
        raise InputError(f"timestamps must increase{' strictly' if strict else ''} "
                         f"(data row {i + 1}: t={float(t[i])!r} after t={float(t[i - 1])!r})", source=source)


# TUM ---------------------------------------------------------------------------------------------
def write_tum(path, trajectory: Trajectory) -> Path:
    """TUM file "t tx ty tz qx qy qz qw" with translation 0 0 0 (rotation-only), readable by evo."""
    q = trajectory.quaternions_xyzw()
    q = q * np.where(q[:, 3:4] < 0, -1.0, 1.0)  # canonical sign: qw >= 0
    data = np.column_stack([trajectory.t, np.zeros((len(q), 3)), q])
    path = Path(path)
    np.savetxt(path, data, fmt=["%.9f", "%d", "%d", "%d", "%.12f", "%.12f", "%.12f", "%.12f"],
               header="timestamp tx ty tz qx qy qz qw", comments="# ")
    return path


def read_tum(path) -> Trajectory:
    """TUM trajectory (translation ignored) -> Trajectory of R_world_from_camera."""
    source = str(path)
    d = read_table(path, 8, "t tx ty tz qx qy qz qw")
    norms = np.linalg.norm(d[:, 4:8], axis=1)
    if (norms < 1e-9).any():
        i = int(np.argmax(norms < 1e-9))
        raise InputError(f"data row {i + 1} has a zero quaternion", source=source)
    _sorted_times(d[:, 0], source, strict=True)
    return Trajectory(d[:, 0], so3.from_quat_xyzw(d[:, 4:8]))


# IMU ---------------------------------------------------------------------------------------------
def write_imu_txt(path, imu: ImuData) -> Path:
    """ECD imu.txt: "t ax ay az gx gy gz" (m/s^2, rad/s)."""
    path = Path(path)
    np.savetxt(path, np.column_stack([imu.t, imu.acc, imu.gyro]), fmt=["%.9f"] + ["%.9g"] * 6)
    return path


def read_imu_txt(path) -> ImuData:
    source = str(path)
    d = read_table(path, 7, "t ax ay az gx gy gz")
    _sorted_times(d[:, 0], source, strict=False)
    return ImuData(d[:, 0], d[:, 1:4], d[:, 4:7])


# angular velocity --------------------------------------------------------------------------------
def write_angular_velocity(path, t, omega) -> Path:
    """Angular velocity "t wx wy wz" (rad/s, camera frame)."""
    t = np.asarray(t, dtype=float).reshape(-1)
    omega = np.asarray(omega, dtype=float).reshape(-1, 3)
    if len(t) != len(omega):
        raise InputError(f"angular velocity: {len(t)} timestamps but {len(omega)} vectors")
    path = Path(path)
    np.savetxt(path, np.column_stack([t, omega]), fmt=["%.9f", "%.12g", "%.12g", "%.12g"],
               header="t wx wy wz (rad/s, camera frame)", comments="# ")
    return path


def read_angular_velocity(path) -> tuple[np.ndarray, np.ndarray]:
    source = str(path)
    d = read_table(path, 4, "t wx wy wz")
    _sorted_times(d[:, 0], source, strict=False)
    return d[:, 0].copy(), d[:, 1:4].copy()
