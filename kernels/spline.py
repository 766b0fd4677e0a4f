"""SO(3) B-spline pose and control-pose Jacobians as Taichi funcs (one time per call).

The math is ``ti_cmax.spline`` (module docstring there) line by line: cumulative form
R = R_s prod_{j=1..n} exp(B~_j Omega_{s+j}), LEFT perturbations R_k <- exp(delta_k) R_k and
R(t) <- exp(sum_j J_j delta_{s+j}) R(t), with J_s = I - M_1, J_{s+j} = M_j - M_{j+1}, J_{s+n} = M_n and
M_j = B~_j P_{j-1} Jl(B~_j Omega_{s+j}) Jr^-1(Omega_{s+j}) R_{s+j}^T  (O(degree), Sommer et al. CVPR 2020).
The numpy class is the test oracle of these funcs.

``spline_funcs(dtype, degree)`` returns ``segment(ctrl, k) -> (Omega_k, N_k)`` (what every time
on a knot interval shares), and ``pose_from_segments(ctrl, om, s, u)`` and ``pose_jacobians(ctrl, om, nm, s, u,
jac_out, row) -> R`` (J_0..J_n written to ``jac_out[row, :]``) that read the intervals' segments from arrays,
where ``ctrl`` is an ndarray of 3x3 matrices and (s, u) come from ``SO3Spline.support`` (computed in float64 on
the host, so no float32 timestamps ever enter a kernel).
"""

import functools
from types import SimpleNamespace

import numpy as np

from .runtime import ensure_init, ti
from .so3 import so3_funcs


def _dtype_of(np_dtype) -> object:
    return ti.f64 if np.dtype(np_dtype) == np.float64 else ti.f32


@functools.cache
def spline_funcs(dtype, degree: int) -> SimpleNamespace:
    """ti.funcs for one float dtype and spline degree (1 linear, 3 cubic)."""
    if degree not in (1, 3):
        raise ValueError(f"spline degree must be 1 or 3, got {degree}")
    g = so3_funcs(dtype)
    n = degree

    @ti.func
    def c(x):
        return ti.cast(x, dtype)

    @ti.func
    def basis(u):
        """Cumulative basis B~_j(u), j = 0..n (Eq. 12 for cubic; (1, u) for linear)."""
        b = ti.Vector([c(1.0)] * (n + 1), dt=dtype)
        if ti.static(n == 1):
            b[1] = u
        else:
            u2 = u * u
            u3 = u2 * u
            b[1] = (c(5.0) + c(3.0) * u - c(3.0) * u2 + u3) / c(6.0)
            b[2] = (c(1.0) + c(3.0) * u + c(3.0) * u2 - c(2.0) * u3) / c(6.0)
            b[3] = u3 / c(6.0)
        return b

    @ti.func
    def segment(ctrl: ti.template(), k):
        """(Omega_k, N_k) of the knot interval from control pose k - 1 to k: Omega_k = log(R_{k-1}^T R_k) and
        N_k = Jr^-1(Omega_k) R_k^T, what every pose and Jacobian on that interval shares (computed once per interval
        rather than once per time: the log and Jr^-1 cost most of a pose's transcendental calls)."""
        r = ctrl[k]
        om = g.log(ctrl[k - 1].transpose() @ r)
        return om, g.jr_inv(om) @ r.transpose()

    @ti.func
    def pose_jacobians(ctrl: ti.template(), om: ti.template(), nm: ti.template(), s, u, jac_out: ti.template(), row):
        """R(s, u) from the control poses and their intervals' ``segment`` (om[k], nm[k] for k = s + 1..s + n); writes
        J_0..J_n into jac_out[row, 0..n]. M_j = B~_j P_{j-1} Jl(B~_j Omega) Jr^-1(Omega) R^T, P_j = P_{j-1}
        exp(B~_j Omega), J_{j-1} = M_{j-1} - M_j (M_0 = I), J_n = M_n. A loop, not an unrolled sequence: Taichi
        transforms the body once (a cubic kernel's start-up 0.7 -> 0.3 s)."""
        b = basis(u)
        p = ctrl[s]
        m_prev = ti.Matrix.identity(dtype, 3)
        for j in range(1, n + 1):
            a_j, jl_j = g.exp_jl(b[j] * om[s + j])
            m = b[j] * (p @ jl_j @ nm[s + j])
            jac_out[row, j - 1] = m_prev - m
            p = p @ a_j
            m_prev = m
        jac_out[row, n] = m_prev
        return p

    @ti.func
    def pose_from_segments(ctrl: ti.template(), om: ti.template(), s, u):
        """R(s, u) from the control poses and their intervals' Omega_k (``segment``); a loop, as in
        ``pose_jacobians``."""
        b = basis(u)
        r = ctrl[s]
        for j in range(1, n + 1):
            r = r @ g.exp(b[j] * om[s + j])
        return r

    return SimpleNamespace(basis=basis, segment=segment, pose_jacobians=pose_jacobians,
                           pose_from_segments=pose_from_segments)


@functools.cache
def _eval_kernel(dtype, degree: int):
    f = spline_funcs(dtype, degree)
    mat3 = ti.types.matrix(3, 3, dtype)
    vec3 = ti.types.vector(3, dtype)

    @ti.kernel
    def k(
        ctrl: ti.types.ndarray(dtype=mat3, ndim=1),
        s: ti.types.ndarray(dtype=ti.i32, ndim=1),
        u: ti.types.ndarray(dtype=dtype, ndim=1),
        om: ti.types.ndarray(dtype=vec3, ndim=1),
        nm: ti.types.ndarray(dtype=mat3, ndim=1),
        out_r: ti.types.ndarray(dtype=mat3, ndim=1),
        out_j: ti.types.ndarray(dtype=mat3, ndim=2),
    ):
        for i in range(1, ctrl.shape[0]):
            om[i], nm[i] = f.segment(ctrl, i)
        for i in range(s.shape[0]):
            out_r[i] = f.pose_jacobians(ctrl, om, nm, s[i], u[i], out_j, i)

    return k


def spline_pose_jacobians(degree: int, control_R: np.ndarray, s: np.ndarray, u: np.ndarray, dtype=np.float32):
    """Evaluate pose (N,3,3) and Jacobians (N, degree+1, 3, 3) in a Taichi kernel (for tests and batch poses)."""
    ensure_init()
    dtype = np.dtype(dtype)
    ctrl = np.ascontiguousarray(control_R, dtype=dtype).reshape(-1, 3, 3)
    s = np.ascontiguousarray(s, dtype=np.int32).reshape(-1)
    u = np.ascontiguousarray(u, dtype=dtype).reshape(-1)
    out_r = np.zeros((len(s), 3, 3), dtype=dtype)
    out_j = np.zeros((len(s), degree + 1, 3, 3), dtype=dtype)
    if len(s):
        _eval_kernel(_dtype_of(dtype), degree)(ctrl, s, u, np.zeros((len(ctrl), 3), dtype),
                                               np.zeros((len(ctrl), 3, 3), dtype), out_r, out_j)
    return out_r, out_j
