"""Rotational motions R_world_from_camera(t) with analytic body-frame angular velocity omega(t).

The ground-truth rotation is integrated on a fine grid (``integration_rate``, 10 kHz by default)
with exact exponential steps at the midpoint angular velocity, R_{k+1} = R_k exp([omega(t_k + dt/2)]x dt),
whose local error is O(dt^3 |omega| |d omega/dt|): about 1e-6 rad after 5 s of the fastest random
motion, far below 0.01 deg. Rotations between grid points are completed with one more exact step
from the previous grid point (not Slerp), so the renderer and the ground truth agree.

Kinds:
- ``random``: sum of seeded sinusoids per axis times a ramp envelope (slow start, growing to the
  peak angular velocity near the end), like the ECD rotation sequences.
- ``pan``: ``turns`` full turns (default 1) about the world vertical axis (y, pointing down) with a smooth
  velocity profile 2 pi turns / T (1 - cos(2 pi t / T)) (zero rate at both ends), plus an optional seeded
  ``wobble``: R(t) = Ry(theta(t)) exp(phi(t)), a tilt phi(t) of sinusoids per axis (0.3 Hz up to
  ``frequency_max``, amplitudes giving a rate of about ``wobble`` rad/s at peak, so a tilt of some 15-25 degrees at
  1 rad/s), at full strength after a 2 s ramp from each end (sin^2), zero with its rate at both ends. The pan stays
  about the world vertical however long it lasts, so multi-turn pans revisit the first turn's map (loop closure).
- ``constant``: a constant rate about a fixed camera-frame axis (star tracking, 4 deg/s).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .. import so3
from ..trajectory import Trajectory


@dataclass(frozen=True, eq=False)
class RotationalMotion:
    """Analytic angular velocity plus its finely integrated rotation."""

    kind: str
    duration: float
    params: dict  # kind-specific parameters (JSON-serialisable)
    grid_t: np.ndarray  # fine integration grid (s)
    grid_R: np.ndarray  # rotations on the grid

    # angular velocity -----------------------------------------------------------------------
    def omega(self, t) -> np.ndarray:
        """Body-frame angular velocity (M, 3) at times t (rad/s)."""
        return _omega(self.kind, self.params, self.duration, np.atleast_1d(np.asarray(t, dtype=np.float64)))

    def rotation(self, t) -> np.ndarray:
        """R_world_from_camera (M, 3, 3) at times t: grid point before t, then one exact midpoint step."""
        t = np.clip(np.atleast_1d(np.asarray(t, dtype=np.float64)), self.grid_t[0], self.grid_t[-1])
        idx = np.clip(np.searchsorted(self.grid_t, t, side="right") - 1, 0, len(self.grid_t) - 1)
        tg = self.grid_t[idx]
        delta = t - tg
        step = so3.exp(self.omega(tg + 0.5 * delta) * delta[:, None])
        return self.grid_R[idx] @ step

    def trajectory(self, rate: float) -> Trajectory:
        """Ground truth sampled at ``rate`` Hz from 0 to the duration (inclusive)."""
        t = sample_times(self.duration, rate)
        return Trajectory(t, self.rotation(t))

    def max_speed(self, t0: float, t1: float, samples: int = 64) -> float:
        """max |omega| over [t0, t1] (dense sampling; omega is smooth)."""
        ts = np.linspace(t0, t1, samples)
        return float(np.linalg.norm(self.omega(ts), axis=1).max())


def sample_times(duration: float, rate: float) -> np.ndarray:
    n = int(np.floor(duration * rate + 1e-9)) + 1
    return np.arange(n) / rate


def _ramp(t: np.ndarray, duration: float, start: float) -> np.ndarray:
    """Envelope growing smoothly from 0 through ``start`` to 1 at the end."""
    x = np.clip(t / duration, 0.0, 1.0)
    s = np.sin(0.5 * np.pi * np.minimum(x / 0.05, 1.0)) ** 2  # 0 -> 1 in the first 5%: start at rest
    return s * (start + (1 - start) * x)


def _omega(kind: str, p: dict, duration: float, t: np.ndarray) -> np.ndarray:
    if kind == "random":
        amp = np.asarray(p["amplitudes"])  # (3, M)
        freq = np.asarray(p["frequencies"])
        phase = np.asarray(p["phases"])
        waves = np.sum(amp[None] * np.sin(2 * np.pi * freq[None] * t[:, None, None] + phase[None]), axis=2)
        return waves * p["scale"] * _ramp(t, duration, p["ramp_start"])[:, None]
    if kind == "pan":
        tc = np.clip(t, 0, duration)
        rate = 2 * np.pi * p.get("turns", 1.0) / duration * (1 - np.cos(2 * np.pi * tc / duration))
        axis = np.asarray(p["axis"])
        if p.get("wobble", 0.0) <= 0:
            return rate[:, None] * axis[None, :]
        phi, phi_dot = _tilt(p, duration, tc)
        # R = Ry(theta) exp(phi): R^T dR/dt = [exp(phi)^T axis theta' + Jr(phi) phi']x
        tilt_t = np.swapaxes(so3.exp(phi), -1, -2)
        return rate[:, None] * (tilt_t @ axis) + np.einsum("nij,nj->ni", so3.right_jacobian(phi), phi_dot)
    if kind == "constant":
        return np.broadcast_to(np.asarray(p["omega"]), (len(t), 3)).copy()
    raise ValueError(f"unknown trajectory kind {kind!r}")


_WOBBLE_RAMP = 2.0  # s: the wobble ramps up (and down) over this span at the pan's ends


def _tilt(p: dict, duration: float, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The pan's wobble: tilt angles phi(t) (M, 3) and their rates, sinusoids per axis under a ramped envelope."""
    amp, freq, phase = (np.asarray(p[k]) for k in ("wobble_amplitudes", "wobble_frequencies", "wobble_phases"))
    w = 2 * np.pi * freq[None]  # (1, 3, M)
    arg = w * t[:, None, None] + phase[None]
    # angle amplitudes wobble * a / w: each sinusoid's rate peaks at wobble * a (a summing to 1 per axis)
    ang = p["wobble"] * amp[None] / w
    waves, waves_dot = np.sum(ang * np.sin(arg), axis=2), np.sum(ang * w * np.cos(arg), axis=2)
    # full strength after a ramp of tau = min(2 s, T / 4) from each end: sin^2 ramps, zero with their rate at the ends
    tau = min(_WOBBLE_RAMP, duration / 4)
    edge = np.minimum(t, duration - t)
    c = np.clip(edge / tau, 0.0, 1.0)
    env = np.sin(0.5 * np.pi * c) ** 2
    env_dot = np.where(c < 1, 0.5 * np.pi / tau * np.sin(np.pi * c), 0.0) * np.where(t <= duration - t, 1.0, -1.0)
    return waves * env[:, None], waves_dot * env[:, None] + waves * env_dot[:, None]


def make_motion(kind: str, duration: float, *, seed: int = 0, max_angular_velocity: float = 5.0,
                frequency_max: float = 1.5, ramp_start: float = 0.1, constant_rate_deg: float = 4.0, axis=(),
                integration_rate: float = 10000.0, turns: float = 1.0, wobble: float = 0.0) -> RotationalMotion:
    """Build and integrate a seeded motion of the given kind starting at R(0) = identity."""
    rng = np.random.default_rng([seed, 11])
    if kind == "random":
        m = 4
        params = {
            "amplitudes": rng.uniform(0.3, 1.0, (3, m)).tolist(),
            "frequencies": rng.uniform(0.15, frequency_max, (3, m)).tolist(),
            "phases": rng.uniform(0, 2 * np.pi, (3, m)).tolist(),
            "ramp_start": float(ramp_start),
            "scale": 1.0,
        }
        # normalise so the peak |omega| over the sequence equals max_angular_velocity
        ts = np.linspace(0, duration, max(2000, int(duration * 2000)))
        peak = np.linalg.norm(_omega(kind, params, duration, ts), axis=1).max()
        params["scale"] = float(max_angular_velocity / peak) if peak > 0 else 0.0
    elif kind == "pan":
        params = {"axis": [0.0, 1.0, 0.0]}
        if turns != 1.0:
            params["turns"] = float(turns)
        if wobble > 0:  # weights summing to 1 per axis: the tilt's rate peaks at about `wobble` rad/s
            m = 3
            amp = rng.uniform(0.3, 1.0, (3, m))
            params.update(wobble=float(wobble), wobble_amplitudes=(amp / amp.sum(axis=1, keepdims=True)).tolist(),
                          wobble_frequencies=rng.uniform(0.3, max(frequency_max, 0.3), (3, m)).tolist(),
                          wobble_phases=rng.uniform(0, 2 * np.pi, (3, m)).tolist())
    elif kind == "constant":
        ax = np.asarray(axis, dtype=float) if len(axis) else rng.normal(size=3)
        ax = ax / np.linalg.norm(ax)
        params = {"omega": (np.radians(constant_rate_deg) * ax).tolist()}
    else:
        raise ValueError(f"unknown trajectory kind {kind!r}")
    n = int(np.ceil(duration * integration_rate))
    grid_t = np.linspace(0.0, duration, n + 1)
    dt = np.diff(grid_t)
    steps = so3.exp(_omega(kind, params, duration, grid_t[:-1] + 0.5 * dt) * dt[:, None])
    grid_R = np.empty((n + 1, 3, 3))
    grid_R[0] = np.eye(3)
    r = np.eye(3)
    for k in range(n):
        r = r @ steps[k]
        grid_R[k + 1] = r
    # re-orthonormalise (round-off only; ~1e-15 per step)
    u, _, vt = np.linalg.svd(grid_R)
    grid_R = u @ vt
    return RotationalMotion(kind, float(duration), params, grid_t, grid_R)
