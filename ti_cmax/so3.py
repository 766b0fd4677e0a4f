"""SO(3) helpers in numpy, vectorized over leading dimensions.

Rotation vectors phi (..., 3) and matrices (..., 3, 3); interoperable with
``scipy.spatial.transform.Rotation`` (same quaternion order x, y, z, w and the same matrix -> quaternion method,
tested against it), but without importing scipy.spatial: it costs ~0.3 s of every command's start-up.
Right Jacobian convention: exp(phi + d) ~= exp(phi) exp(Jr(phi) d).
"""
from __future__ import annotations

import numpy as np

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
    """Rotation matrix(es) -> rotation vector(s) in the ball |phi| <= pi (through the unit quaternion: robust near
    pi, where the matrix's antisymmetric part vanishes)."""
    r = np.asarray(r, dtype=float)
    q = to_quat_xyzw(r)
    q = np.where(q[:, 3:] < 0, -q, q)  # w >= 0: angle in [0, pi]
    vnorm = np.linalg.norm(q[:, :3], axis=1)
    angle = 2.0 * np.arctan2(vnorm, q[:, 3])
    small = angle <= 1e-3
    a2 = angle * angle
    # angle / sin(angle / 2), by its series near 0 (2 + a^2/12 + 7 a^4/2880)
    scale = np.where(small, 2.0 + a2 / 12.0 + 7.0 * a2 * a2 / 2880.0,
                     angle / np.sin(0.5 * np.where(small, 1.0, angle)))
    return (scale[:, None] * q[:, :3]).reshape(r.shape[:-2] + (3,))


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
    """Rotation matrix(es) -> unit quaternions (N, 4), x, y, z, w, by the largest of the four candidates built
    from the trace and the diagonal (Markley 2008, as scipy's Rotation.from_matrix; a nearly orthonormal matrix
    gives the quaternion of its nearest rotation)."""
    m = np.asarray(r, dtype=float).reshape(-1, 3, 3)
    diag = np.stack([m[:, 0, 0], m[:, 1, 1], m[:, 2, 2]], axis=1)
    trace = diag.sum(axis=1)
    choice = np.argmax(np.concatenate([diag, trace[:, None]], axis=1), axis=1)
    q = np.empty((len(m), 4))
    w = choice == 3
    q[w, 0] = m[w, 2, 1] - m[w, 1, 2]
    q[w, 1] = m[w, 0, 2] - m[w, 2, 0]
    q[w, 2] = m[w, 1, 0] - m[w, 0, 1]
    q[w, 3] = 1.0 + trace[w]
    for i in range(3):
        j, k = (i + 1) % 3, (i + 2) % 3
        sel = choice == i
        q[sel, i] = 1.0 - trace[sel] + 2.0 * m[sel, i, i]
        q[sel, j] = m[sel, j, i] + m[sel, i, j]
        q[sel, k] = m[sel, k, i] + m[sel, i, k]
        q[sel, 3] = m[sel, k, j] - m[sel, j, k]
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def euler_xyz(r: np.ndarray) -> np.ndarray:
    """Rotation matrix(es) (N, 3, 3) -> extrinsic x-y-z Euler angles (N, 3) in radians, roll about x, pitch about y
    in [-pi/2, pi/2], yaw about z, R = Rz(yaw) Ry(pitch) Rx(roll): scipy's ``as_euler("xyz")``, gimbal lock
    (|pitch| = pi/2) included, where yaw is 0 and roll takes the whole turn about the vertical."""
    m = np.asarray(r, dtype=float).reshape(-1, 3, 3)
    cos_pitch = np.hypot(m[:, 0, 0], m[:, 1, 0])
    pitch = np.arctan2(-m[:, 2, 0], cos_pitch)
    lock = cos_pitch < 1e-7
    roll = np.where(lock, np.arctan2(-m[:, 1, 2], m[:, 1, 1]), np.arctan2(m[:, 2, 1], m[:, 2, 2]))
    yaw = np.where(lock, 0.0, np.arctan2(m[:, 1, 0], m[:, 0, 0]))
    return np.stack([roll, pitch, yaw], axis=1)


def from_quat_xyzw(q: np.ndarray) -> np.ndarray:
    """Quaternions (N, 4), x, y, z, w (normalised here) -> rotation matrices (N, 3, 3)."""
    q = np.asarray(q, dtype=float).reshape(-1, 4)
    x, y, z, w = (q / np.linalg.norm(q, axis=1, keepdims=True)).T
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], axis=1),
        np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], axis=1),
        np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], axis=1),
    ], axis=1)


def slerp(times: np.ndarray, rotations: np.ndarray, query: np.ndarray) -> np.ndarray:
    """Rotations at ``query`` times (within [times[0], times[-1]]) interpolated along the geodesic between the
    samples around each: R_i exp(a log(R_i^T R_{i+1})), a the fraction of the interval (as scipy's Slerp)."""
    times = np.asarray(times, dtype=float)
    rotations = np.asarray(rotations, dtype=float)
    query = np.asarray(query, dtype=float)
    i = np.clip(np.searchsorted(times, query, side="left") - 1, 0, len(times) - 2)
    alpha = (query - times[i]) / (times[i + 1] - times[i])
    rel = log(np.swapaxes(rotations[i], -1, -2) @ rotations[i + 1])
    return rotations[i] @ exp(alpha[:, None] * rel)


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
