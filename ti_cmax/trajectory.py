"""A sampled rotation trajectory R_world_from_camera(t), queryable at any time.

Used for ground truth, front-end output (integrated omega), IMU dead reckoning and spline
samples. Between samples the rotation is interpolated by Slerp; outside, it is held constant.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import so3
from .errors import InputError


@dataclass(frozen=True, eq=False)
class Trajectory:
    t: np.ndarray  # (N,) seconds, strictly increasing
    R: np.ndarray  # (N, 3, 3) R_world_from_camera

    def __post_init__(self):
        t = np.ascontiguousarray(self.t, dtype=np.float64).reshape(-1)
        r = np.ascontiguousarray(self.R, dtype=np.float64).reshape(-1, 3, 3)
        if len(t) != len(r):
            raise InputError(f"trajectory has {len(t)} timestamps but {len(r)} rotations")
        if len(t) == 0:
            raise InputError("trajectory is empty")
        if len(t) > 1 and np.any(np.diff(t) <= 0):
            i = int(np.argmax(np.diff(t) <= 0)) + 1
            raise InputError(f"trajectory timestamps must increase strictly (sample {i}, t={float(t[i])!r})")
        object.__setattr__(self, "t", t)
        object.__setattr__(self, "R", r)

    def __len__(self) -> int:
        return len(self.t)

    @property
    def rotations(self):
        """The samples as a ``scipy.spatial.transform.Rotation`` (imported here: it costs ~0.3 s of start-up)."""
        from scipy.spatial.transform import Rotation

        return Rotation.from_matrix(self.R)

    @property
    def t_start(self) -> float:
        return float(self.t[0])

    @property
    def t_end(self) -> float:
        return float(self.t[-1])

    def at(self, times: np.ndarray | float) -> np.ndarray:
        """Rotation matrices at arbitrary times, (M, 3, 3) (Slerp; clamped at the ends)."""
        times = np.atleast_1d(np.asarray(times, dtype=np.float64))
        if len(self.t) == 1:
            return np.broadcast_to(self.R[0], (len(times), 3, 3)).copy()
        clamped = np.clip(times, self.t[0], self.t[-1])
        # Slerp only over the samples of the intervals queried (its interval of t: searchsorted left - 1, the first
        # sample itself in interval 0): a query near one time costs O(1), not O(samples); the same values
        interval = np.maximum(np.searchsorted(self.t, clamped, side="left") - 1, 0)
        lo, hi = int(interval.min()), int(interval.max()) + 2
        return so3.slerp(self.t[lo:hi], self.R[lo:hi], clamped)

    def resampled(self, times: np.ndarray) -> "Trajectory":
        return Trajectory(np.asarray(times, dtype=float), self.at(times))

    def slice_time(self, t_start: float, t_end: float) -> "Trajectory":
        keep = (self.t >= t_start) & (self.t <= t_end)
        return Trajectory(self.t[keep], self.R[keep])

    def aligned_to(self, reference: "Trajectory", t0: float) -> "Trajectory":
        """Align at one time (CONVENTIONS.md): R_aligned(t) = R_ref(t0) R(t0)^T R(t)."""
        offset = reference.at(t0)[0] @ self.at(t0)[0].T
        return Trajectory(self.t, offset @ self.R)

    def left_multiplied(self, r: np.ndarray) -> "Trajectory":
        return Trajectory(self.t, np.asarray(r) @ self.R)

    def quaternions_xyzw(self) -> np.ndarray:
        return so3.to_quat_xyzw(self.R)

    @classmethod
    def from_quaternions(cls, t: np.ndarray, q_xyzw: np.ndarray) -> "Trajectory":
        return cls(t, so3.from_quat_xyzw(q_xyzw))
