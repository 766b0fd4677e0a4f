"""SO(3) helpers in numpy, vectorized over leading dimensions.

Rotation vectors phi (..., 3) and matrices (..., 3, 3); interoperable with
``scipy.spatial.transform.Rotation`` (``Rotation.from_matrix(exp(phi)).as_rotvec() == phi``).
Right Jacobian convention: exp(phi + d) ~= exp(phi) exp(Jr(phi) d).
"""
from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

_SMALL = 1e-8


def hat(v: np.ndarray) -> np.ndarray:
    """Skew-symmetric matrix [v]x such that hat(v) @ w == cross(v, w)."""
    v = np.asarray(v, dtype=float)
    out = np.zeros(v.shape[:-1] + (3, 3))
    out[..., 0, 1], out[..., 0, 2] = -v[..., 2], v[..., 1]
    out[..., 1, 0], out[..., 1, 2] = v[..., 2], -v[..., 0]
    out[..., 2, 0], out[..., 2, 1] = -v[..., 1], v[..., 0]
    return out


def vee(m: np.ndarray) -> np.ndarray:
    """Inverse of hat (uses the antisymmetric part)."""
    m = np.asarray(m, dtype=float)
    return 0.5 * np.stack(
        [m[..., 2, 1] - m[..., 1, 2], m[..., 0, 2] - m[..., 2, 0], m[..., 1, 0] - m[..., 0, 1]], axis=-1
    )


def _coeffs(theta: np.ndarray):
    """A = sin(t)/t, B = (1-cos t)/t^2, C = (t - sin t)/t^3 with Taylor series near 0."""
    t2 = theta * theta
    small = theta < 1e-4
    ts = np.where(small, 1.0, theta)
    a = np.where(small, 1 - t2 / 6 + t2 * t2 / 120, np.sin(ts) / ts)
    b = np.where(small, 0.5 - t2 / 24 + t2 * t2 / 720, (1 - np.cos(ts)) / (ts * ts))
    c = np.where(small, 1 / 6 - t2 / 120 + t2 * t2 / 5040, (ts - np.sin(ts)) / (ts**3))
    return a, b, c


def exp(phi: np.ndarray) -> np.ndarray:
    """Rodrigues: rotation vector(s) -> rotation matrix(es)."""
    phi = np.asarray(phi, dtype=float)
    theta = np.linalg.norm(phi, axis=-1)
    a, b, _ = _coeffs(theta)
    k = hat(phi)
    eye = np.broadcast_to(np.eye(3), k.shape)
    return eye + a[..., None, None] * k + b[..., None, None] * (k @ k)


def log(r: np.ndarray) -> np.ndarray:
    """Rotation matrix(es) -> rotation vector(s) in the ball |phi| <= pi (robust near pi via scipy)."""
    r = np.asarray(r, dtype=float)
    flat = r.reshape(-1, 3, 3)
    out = Rotation.from_matrix(flat).as_rotvec()
    return out.reshape(r.shape[:-2] + (3,))


def right_jacobian(phi: np.ndarray) -> np.ndarray:
    """Jr(phi) = I - B [phi]x + C [phi]x^2."""
    phi = np.asarray(phi, dtype=float)
    theta = np.linalg.norm(phi, axis=-1)
    _, b, c = _coeffs(theta)
    k = hat(phi)
    eye = np.broadcast_to(np.eye(3), k.shape)
    return eye - b[..., None, None] * k + c[..., None, None] * (k @ k)


def left_jacobian(phi: np.ndarray) -> np.ndarray:
    """Jl(phi) = Jr(-phi)."""
    return right_jacobian(-np.asarray(phi, dtype=float))


def right_jacobian_inv(phi: np.ndarray) -> np.ndarray:
    """Inverse of the right Jacobian: I + 1/2 [phi]x + (1/t^2 - (1+cos t)/(2 t sin t)) [phi]x^2."""
    phi = np.asarray(phi, dtype=float)
    theta = np.linalg.norm(phi, axis=-1)
    small = theta < 1e-4
    ts = np.where(small, 1.0, theta)
    d = np.where(small, 1 / 12 + theta**2 / 720, 1 / ts**2 - (1 + np.cos(ts)) / (2 * ts * np.sin(ts)))
    k = hat(phi)
    eye = np.broadcast_to(np.eye(3), k.shape)
    return eye + 0.5 * k + d[..., None, None] * (k @ k)


def geodesic_angle(r_a: np.ndarray, r_b: np.ndarray) -> np.ndarray:
    """Angle (rad) of R_a^T R_b, Eq. (23) of the paper, computed stably via log."""
    rel = np.swapaxes(r_a, -1, -2) @ r_b
    return np.linalg.norm(log(rel), axis=-1)


def spread_correction(step_weights: np.ndarray, phi: np.ndarray) -> np.ndarray:
    """Left corrections (n + 1, 3, 3) that spread a loop's rotation error phi along a chain of n + 1 poses.

    They solve the linearized SO(3) pose graph of the chain: left increments x_0 .. x_n minimizing
    sum_k |x_{k+1} - x_k|^2 / w_k (the smoothness priors: relative rotations are kept, an edge of weight w_k
    may absorb more error) with x_0 = 0 (the first visit) and x_n = phi (the loop constraint). The minimizer is
    x_k = s_k phi with s_k = sum_{j<k} w_j / sum_j w_j; the corrections are exp(x_k).
    """
    w = np.asarray(step_weights, dtype=float).reshape(-1)
    total = float(w.sum())
    s = np.concatenate([[0.0], np.cumsum(w)]) / total if total > 0 else np.linspace(0.0, 1.0, len(w) + 1)
    return exp(s[:, None] * np.asarray(phi, dtype=float)[None, :])


def to_quat_xyzw(r: np.ndarray) -> np.ndarray:
    return Rotation.from_matrix(np.asarray(r).reshape(-1, 3, 3)).as_quat()


def from_quat_xyzw(q: np.ndarray) -> np.ndarray:
    return Rotation.from_quat(np.asarray(q, dtype=float).reshape(-1, 4)).as_matrix()


def integrate_angular_velocity(t: np.ndarray, omega: np.ndarray, r0: np.ndarray | None = None) -> np.ndarray:
    """Integrate body-frame angular velocity samples (dR/dt = R [omega]x) with the midpoint rule.

    Returns one rotation per sample time; R(t[0]) = r0 (identity by default).
    """
    t = np.asarray(t, dtype=float)
    omega = np.asarray(omega, dtype=float).reshape(-1, 3)
    out = np.empty((len(t), 3, 3))
    out[0] = np.eye(3) if r0 is None else r0
    if len(t) > 1:
        dt = np.diff(t)[:, None]
        steps = exp(0.5 * (omega[:-1] + omega[1:]) * dt)
        for i in range(1, len(t)):
            out[i] = out[i - 1] @ steps[i - 1]
    return out
