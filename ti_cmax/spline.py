"""Continuous-time rotation trajectories: linear and cumulative cubic B-splines on SO(3) (numpy, float64).

Control poses are uniformly spaced: control pose k sits at knot time ``t0 + k * dt``.

* Linear (paper Eq. 9), t in [t_i, t_i+1):  R(t) = R_i exp(u Omega_{i+1}),  u = (t - t_i) / dt.
* Cubic (Eq. 10-12), t in [t_i, t_i+1):     R(t) = R_{i-1} prod_{j=1..3} exp(B~_j(u) Omega_{i+j-1}),
  using the four control poses of knots i-1 .. i+2 (so the cubic spline is defined on [t0 + dt, t0 + (M-2) dt]).

with Omega_k = log(R_{k-1}^T R_k). Both are the cumulative form R(t) = R_s prod_{j=1..n} exp(B~_j Omega_{s+j})
with first control index s and n = degree (the linear case has B~_1 = u); one code path serves both.

Perturbation convention (used everywhere: numpy, Taichi funcs, the panoramic IWE gradient, the optimizer):
LEFT (world-frame) perturbations. A control-pose update is ``R_k <- exp(delta_k) R_k`` and the pose responds as
``R(t) <- exp(sum_k J_k delta_k) R(t)`` to first order; ``jacobians`` returns the 3x3 blocks J_k of the
``degree + 1`` control poses that R(t) depends on (they sum to the identity). A rotated bearing X' = R(t) b then
moves by dX' = -[X']x sum_k J_k delta_k. The blocks are computed in O(degree) as in Sommer et al., CVPR 2020:

    omega = delta_s + sum_j M_j (delta_{s+j} - delta_{s+j-1}),
    M_j   = B~_j P_{j-1} Jl(B~_j Omega_{s+j}) Jr^-1(Omega_{s+j}) R_{s+j}^T,
    P_{j-1} = R_s prod_{l<j} exp(B~_l Omega_{s+l}),

so J_s = I - M_1, J_{s+j} = M_j - M_{j+1}, J_{s+n} = M_n. ``kernels/spline.py`` implements the same formulas.
"""
from __future__ import annotations

import math

import numpy as np

from . import so3
from .trajectory import Trajectory

#: Cumulative cubic basis matrix of Eq. (12): B~(u) = C @ (1, u, u^2, u^3).
CUBIC_CUMULATIVE = np.array(
    [[6.0, 0.0, 0.0, 0.0], [5.0, 3.0, -3.0, 1.0], [1.0, 3.0, 3.0, -2.0], [0.0, 0.0, 0.0, 1.0]]
) / 6.0

# Relative tolerance (in units of dt) for times just outside the valid range (float round-off).
_EDGE_TOL = 1e-9


def cumulative_basis(degree: int, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Cumulative basis B~_j(u), j = 0..degree, and its u-derivative, both (..., degree + 1)."""
    u = np.asarray(u, dtype=float)
    if degree == 1:
        b = np.stack([np.ones_like(u), u], axis=-1)
        db = np.stack([np.zeros_like(u), np.ones_like(u)], axis=-1)
    elif degree == 3:
        powers = np.stack([np.ones_like(u), u, u * u, u * u * u], axis=-1)
        dpowers = np.stack([np.zeros_like(u), np.ones_like(u), 2 * u, 3 * u * u], axis=-1)
        b = powers @ CUBIC_CUMULATIVE.T
        db = dpowers @ CUBIC_CUMULATIVE.T
    else:
        raise ValueError(f"spline degree must be 1 (linear) or 3 (cubic), got {degree}")
    return b, db


def blending_basis(degree: int, u: np.ndarray) -> np.ndarray:
    """Ordinary (non-cumulative) B-spline weights b_j = B~_j - B~_{j+1}, (..., degree + 1); they sum to 1."""
    b, _ = cumulative_basis(degree, u)
    nxt = np.concatenate([b[..., 1:], np.zeros_like(b[..., :1])], axis=-1)
    return b - nxt


class SO3Spline:
    """Uniform B-spline (degree 1 or 3) on SO(3); see the module docstring for formulas and conventions.

    ``control_R`` is a mutable (M, 3, 3) float64 array; the back-end updates it in place (``retract``) or grows it
    (``append``, ``fit_new_segment``).
    """

    def __init__(self, degree: int, t0: float, dt: float, control_R: np.ndarray):
        if degree not in (1, 3):
            raise ValueError(f"spline degree must be 1 (linear) or 3 (cubic), got {degree}")
        if not dt > 0:
            raise ValueError(f"knot spacing dt must be positive, got {dt}")
        self.degree = int(degree)
        self.t0 = float(t0)
        self.dt = float(dt)
        self.control_R = np.array(control_R, dtype=np.float64).reshape(-1, 3, 3)

    # ---- structure -------------------------------------------------------------------------------------------
    @property
    def order(self) -> int:
        """Number of control poses each time depends on (2 linear, 4 cubic)."""
        return self.degree + 1

    @property
    def num_control(self) -> int:
        return len(self.control_R)

    def knot_times(self) -> np.ndarray:
        """Time of each control pose, (M,)."""
        return self.t0 + self.dt * np.arange(self.num_control)

    def valid_time_range(self) -> tuple[float, float]:
        """[start, end] where the spline is defined: linear [t_0, t_{M-1}], cubic [t_1, t_{M-2}]."""
        lead = (self.degree - 1) // 2  # 0 linear, 1 cubic
        if self.num_control < self.order:
            raise ValueError(f"a degree-{self.degree} spline needs at least {self.order} control poses")
        return self.t0 + lead * self.dt, self.t0 + (self.num_control - 1 - lead) * self.dt

    def copy(self) -> "SO3Spline":
        return SO3Spline(self.degree, self.t0, self.dt, self.control_R.copy())

    def append(self, control_R: np.ndarray) -> "SO3Spline":
        """Append control poses (K, 3, 3) or (3, 3) at the next knots; returns self."""
        new = np.asarray(control_R, dtype=np.float64).reshape(-1, 3, 3)
        self.control_R = np.concatenate([self.control_R, new], axis=0)
        return self

    def retract(self, delta: np.ndarray, first: int = 0) -> "SO3Spline":
        """Apply left updates R_k <- exp(delta_k) R_k to control poses first .. first + len(delta) - 1; returns self."""
        delta = np.asarray(delta, dtype=np.float64).reshape(-1, 3)
        sl = slice(first, first + len(delta))
        self.control_R[sl] = so3.exp(delta) @ self.control_R[sl]
        return self

    def support(self, times: np.ndarray | float) -> tuple[np.ndarray, np.ndarray]:
        """First control index s (int64) and normalized time u in [0, 1] for each time.

        R(t) depends on control poses s .. s + degree. Raises ValueError outside ``valid_time_range``.
        """
        times = np.atleast_1d(np.asarray(times, dtype=np.float64))
        lead = (self.degree - 1) // 2
        start, end = self.valid_time_range()
        tol = _EDGE_TOL * self.dt + 1e-12 * max(abs(start), abs(end))
        if times.size and (times.min() < start - tol or times.max() > end + tol):
            raise ValueError(
                f"times [{times.min():.9f}, {times.max():.9f}] outside the spline's valid range "
                f"[{start:.9f}, {end:.9f}]"
            )
        x = (times - self.t0) / self.dt - lead
        i = np.clip(np.floor(x), 0, self.num_control - self.order).astype(np.int64)
        u = np.clip(x - i, 0.0, 1.0)
        return i, u

    # ---- evaluation --------------------------------------------------------------------------------------------
    def _chain(self, s: np.ndarray, u: np.ndarray):
        """Shared per-time quantities: basis, Omega_{s+j}, partial products P_j (j = 0..n)."""
        n = self.degree
        b, db = cumulative_basis(n, u)
        ctrl = self.control_R
        # Omega depends on the control index only: one log per distinct index, not per time (many times share a
        # segment; the same matrices give the same logs, so the values are unchanged)
        first, inverse = np.unique(s, return_inverse=True)
        idx = first[:, None] + np.arange(n + 1)  # (F, n + 1): the control poses of each distinct index
        rel = np.swapaxes(ctrl[idx[:, :-1]], -1, -2) @ ctrl[idx[:, 1:]]  # (F, n, 3, 3), one log call for all
        omegas = so3.log(rel)[inverse.reshape(-1)]
        prods = [ctrl[s]]
        for j in range(1, n + 1):
            prods.append(prods[-1] @ so3.exp(b[:, j, None] * omegas[:, j - 1]))
        return b, db, omegas, prods

    def evaluate(self, times: np.ndarray | float) -> np.ndarray:
        """R(t) for each time, (N, 3, 3)."""
        return self.evaluate_at(*self.support(times))

    def evaluate_at(self, s: np.ndarray, u: np.ndarray) -> np.ndarray:
        """R for given first control indices s and normalized times u (as returned by ``support``)."""
        s, u = np.atleast_1d(np.asarray(s, dtype=np.int64)), np.atleast_1d(np.asarray(u, dtype=float))
        return self._chain(s, u)[3][-1]

    def angular_velocity(self, times: np.ndarray | float) -> np.ndarray:
        """Body-frame angular velocity omega(t) (dR/dt = R [omega]x), (N, 3) rad/s."""
        s, u = self.support(times)
        b, db, omegas, _ = self._chain(s, u)
        w = np.zeros((len(s), 3))
        for j in range(1, self.degree + 1):
            a_j = so3.exp(b[:, j, None] * omegas[:, j - 1])
            w = np.einsum("nji,nj->ni", a_j, w) + db[:, j, None] * omegas[:, j - 1] / self.dt
        return w

    def jacobians(self, times: np.ndarray | float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Pose and its Jacobians w.r.t. the control poses it depends on (left perturbations, module docstring).

        Returns (first_index (N,), R (N, 3, 3), J (N, degree + 1, 3, 3)) where J[:, j] belongs to control
        pose first_index + j: R(t) <- exp(sum_j J[:, j] delta_{first+j}) R(t).
        """
        return self.jacobians_at(*self.support(times))

    def jacobians_at(self, s: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``jacobians`` for given (s, u) as returned by ``support``."""
        s, u = np.atleast_1d(np.asarray(s, dtype=np.int64)), np.atleast_1d(np.asarray(u, dtype=float))
        n = self.degree
        b, _, omegas, prods = self._chain(s, u)
        ctrl = self.control_R
        eye = np.broadcast_to(np.eye(3), (len(s), 3, 3))
        m = []
        for j in range(1, n + 1):
            om = omegas[:, j - 1]
            mj = prods[j - 1] @ so3.left_jacobian(b[:, j, None] * om) @ so3.right_jacobian_inv(om)
            m.append(b[:, j, None, None] * (mj @ np.swapaxes(ctrl[s + j], -1, -2)))
        jac = np.empty((len(s), n + 1, 3, 3))
        jac[:, 0] = eye - m[0]
        for j in range(1, n):
            jac[:, j] = m[j - 1] - m[j]
        jac[:, n] = m[n - 1]
        return s, prods[-1], jac

    def to_trajectory(self, rate: float, t_start: float | None = None, t_end: float | None = None) -> Trajectory:
        """Sample the spline at ``rate`` Hz over [t_start, t_end] (default: the valid range, end included)."""
        start, end = self.valid_time_range()
        t_start = start if t_start is None else max(start, float(t_start))
        t_end = end if t_end is None else min(end, float(t_end))
        n = max(int(math.floor((t_end - t_start) * rate + 1e-9)), 0)
        times = t_start + np.arange(n + 1) / rate
        if times[-1] < t_end - 1e-12:
            times = np.append(times, t_end)
        return Trajectory(times, self.evaluate(times))

    # ---- fitting (lift-solve-retract, Sec. III-C2) ---------------------------------------------------------------
    def num_control_to_cover(self, t_end: float) -> int:
        """Number of control poses needed so that the valid range reaches t_end."""
        lead = (self.degree - 1) // 2
        return int(math.ceil((t_end - self.t0) / self.dt - _EDGE_TOL)) + 1 + lead

    def fit_new_segment(
        self,
        times: np.ndarray,
        rotations: np.ndarray,
        first_free: int,
        refine_iters: int = 0,
        smoothness: float = 1e-4,
    ) -> "SO3Spline":
        """Fit control poses ``first_free ..`` to samples (t_k, R_k), keeping earlier ones fixed; returns self.

        Control poses are appended so that the valid range covers max(times). Lift-solve-retract: with the
        offset R_off = R at the first sample, lift every control pose and sample to x = log(R_off^T R), solve
        the linear least squares  sum_k |sum_j b_j(u_k) x_{s_k+j} - y_k|^2  (ordinary B-spline weights, fixed
        x moved to the right-hand side) plus ``smoothness`` times the squared second differences of x, and retract
        R = R_off exp(x). The smoothness term decides the control poses that samples barely reach: a cubic pose
        whose only sample sits 0.2 knot intervals into its support has basis weight 0.0013 (squared 2e-6), and
        with 1e-6 the fit amplified that sample's residual into a 30-50 deg pose (seen on RTPT poses resampled at
        100 Hz); 1e-4 makes such poses extrapolate linearly and leaves well-sampled ones unchanged (< 0.01 deg). ``refine_iters`` Gauss-Newton steps on
        the manifold (residual log(R_k R(t_k)^T), the spline's own Jacobians) then remove the linearization
        error of the lift, so a spline is reproduced from its own samples (to 1e-6 rad: the smoothness term).
        """
        times = np.asarray(times, dtype=np.float64).reshape(-1)
        rotations = np.asarray(rotations, dtype=np.float64).reshape(-1, 3, 3)
        if len(times) == 0 or len(times) != len(rotations):
            raise ValueError("fit needs matching, non-empty times and rotations")
        m_needed = max(self.num_control_to_cover(times.max()), first_free + 1, self.order)
        if m_needed > self.num_control:
            fill = self.control_R[-1] if self.num_control else rotations[0]
            self.append(np.broadcast_to(fill, (m_needed - self.num_control, 3, 3)))
        free = np.arange(first_free, self.num_control)
        if len(free) == 0:
            return self

        # lift
        r_off = rotations[0]
        s, u = self.support(times)
        # lift only the poses the fit reads (the samples' supports, the free poses and their second-difference
        # neighbours): the earlier ones never enter it, and a long trajectory has thousands
        lo = max(0, min(int(s.min()), first_free - 2))
        x = np.zeros((self.num_control, 3))
        x[lo:] = so3.log(r_off.T @ self.control_R[lo:])
        y = so3.log(r_off.T @ rotations)
        w = blending_basis(self.degree, u)  # (K, order)
        a, rhs = self._design(s, w, free, x, y)
        reg = self._second_difference(free, x)
        sol = self._solve(a, rhs, reg, smoothness)
        x[free] = sol.reshape(-1, 3)
        # retract
        self.control_R[free] = r_off @ so3.exp(x[free])

        return self._refine(times, rotations, free, refine_iters, smoothness)

    def _refine(self, times, rotations, free, iters: int, smoothness: float) -> "SO3Spline":
        """Gauss-Newton steps on the manifold over the ``free`` control poses (residual log(R_k R(t_k)^T))."""
        for _ in range(iters):
            s, r_t, jac = self.jacobians(times)
            res = so3.log(rotations @ np.swapaxes(r_t, -1, -2)).reshape(-1)
            a = self._jacobian_matrix(s, jac, free)
            reg = self._second_difference(free, np.zeros((self.num_control, 3)))
            delta = self._solve(a, res, reg, smoothness).reshape(-1, 3)
            self.control_R[free] = so3.exp(delta) @ self.control_R[free]
        return self

    @classmethod
    def fit(
        cls, degree: int, dt: float, times: np.ndarray, rotations: np.ndarray, t0: float | None = None,
        refine_iters: int = 2,
    ) -> "SO3Spline":
        """A spline whose valid range starts at t0 (default times[0]) fitted to all samples (no pose fixed).

        The lift about one offset rotation holds within half a turn of it, so samples that turn further are lifted
        in consecutive segments, each within ``LIFT_SEGMENT_ANGLE`` of its first sample (each segment's new control
        poses fitted with the earlier ones fixed); the Gauss-Newton steps then refine all poses together."""
        times = np.asarray(times, dtype=np.float64).reshape(-1)
        rotations = np.asarray(rotations, dtype=np.float64).reshape(-1, 3, 3)
        start = float(times[0]) if t0 is None else float(t0)
        lead = (degree - 1) // 2
        spline = cls(degree, start - lead * dt, dt, np.broadcast_to(rotations[0], (degree + 1, 3, 3)))
        ends = _lift_segment_ends(rotations)
        if len(ends) == 1:
            return spline.fit_new_segment(times, rotations, 0, refine_iters=refine_iters)
        begin = 0
        for end in ends:
            # the poses after the last one the previous segment's samples reach are free; its samples stay in the
            # fit so that the new poses join the fixed ones smoothly
            first_free = 0 if begin == 0 else int(spline.support(times[begin - 1 : begin])[0][0]) + spline.order
            first_free = min(first_free, spline.num_control_to_cover(times[end - 1]) - 1)
            lo = 0 if begin == 0 else max(0, np.searchsorted(times, times[begin] - spline.order * dt))
            spline.fit_new_segment(times[lo:end], rotations[lo:end], first_free)
            begin = end
        return spline._refine(times, rotations, np.arange(spline.num_control), refine_iters, 1e-4)

    # helpers of the fit
    def _design(self, s, w, free, x, y):
        """Sparse design matrix over the free lifted poses and right-hand side (fixed poses moved over)."""
        k = len(s)
        col_of = np.full(self.num_control, -1)
        col_of[free] = np.arange(len(free))
        rows, cols, vals = [], [], []
        rhs = y.copy()
        for j in range(self.order):
            idx = s + j
            c = col_of[idx]
            is_free = c >= 0
            rhs[~is_free] -= w[~is_free, j, None] * x[idx[~is_free]]
            for d in range(3):
                rows.append(3 * np.nonzero(is_free)[0] + d)
                cols.append(3 * c[is_free] + d)
                vals.append(w[is_free, j])
        a = _matrix(np.concatenate(vals), np.concatenate(rows), np.concatenate(cols), (3 * k, 3 * len(free)))
        return a, rhs.reshape(-1)

    def _jacobian_matrix(self, s, jac, free):
        k = len(s)
        col_of = np.full(self.num_control, -1)
        col_of[free] = np.arange(len(free))
        rows, cols, vals = [], [], []
        for j in range(self.order):
            c = col_of[s + j]
            sel = np.nonzero(c >= 0)[0]
            for d in range(3):
                for e in range(3):
                    rows.append(3 * sel + d)
                    cols.append(3 * c[sel] + e)
                    vals.append(jac[sel, j, d, e])
        return _matrix(np.concatenate(vals), np.concatenate(rows), np.concatenate(cols), (3 * k, 3 * len(free)))

    def _second_difference(self, free, x):
        """Rows x_{i-1} - 2 x_i + x_{i+1} touching a free pose: (sparse matrix on free, constant part)."""
        col_of = np.full(self.num_control, -1)
        col_of[free] = np.arange(len(free))
        centers = [i for i in range(max(1, int(free.min()) - 1), self.num_control - 1)
                   if np.any(col_of[i - 1 : i + 2] >= 0)]
        rows, cols, vals = [], [], []
        const = np.zeros((len(centers), 3))
        for r, i in enumerate(centers):
            for idx, coef in ((i - 1, 1.0), (i, -2.0), (i + 1, 1.0)):
                if col_of[idx] >= 0:
                    for d in range(3):
                        rows.append(3 * r + d)
                        cols.append(3 * col_of[idx] + d)
                        vals.append(coef)
                else:
                    const[r] += coef * x[idx]
        d = _matrix(np.asarray(vals, float), np.asarray(rows, np.int64), np.asarray(cols, np.int64),
                    (3 * len(centers), 3 * len(free)))
        return d, const.reshape(-1)

    @staticmethod
    def _solve(a, rhs, reg, weight):
        d, const = reg
        b = a.T @ rhs - weight * (d.T @ const)
        if isinstance(a, np.ndarray):
            return np.linalg.solve(a.T @ a + weight * (d.T @ d) + 1e-12 * np.eye(a.shape[1]), b)
        import scipy.sparse as sp
        import scipy.sparse.linalg as spla

        lhs = (a.T @ a + weight * (d.T @ d) + 1e-12 * sp.identity(a.shape[1])).tocsc()
        return np.atleast_1d(spla.spsolve(lhs, b))


LIFT_SEGMENT_ANGLE = math.pi / 2  # a lift segment's samples stay this close to its first one (well inside pi)


def _lift_segment_ends(rotations: np.ndarray) -> list[int]:
    """Ends (exclusive) of consecutive sample segments, each within LIFT_SEGMENT_ANGLE of its first sample."""
    ends, first = [], 0
    while first < len(rotations):
        angle = so3.geodesic_angle(rotations[first], rotations[first:])
        beyond = np.nonzero(angle > LIFT_SEGMENT_ANGLE)[0]
        end = first + (int(beyond[0]) if len(beyond) else len(angle))
        ends.append(max(end, first + 1))
        first = ends[-1]
    return ends


DENSE_FIT_COLUMNS = 300  # fits over at most this many parameters (100 free poses) solve dense...
DENSE_FIT_CELLS = 2_000_000  # ... when the dense matrix stays small too (16 MB: e.g. 1 kHz IMU samples over 100 poses)


def _matrix(vals, rows, cols, shape):
    """The fit's matrix from (value, row, col) triplets (duplicates summed): dense for the sliding window's small
    fits (a few dozen parameters: numpy, and no scipy.sparse import, ~0.1 s of every run's start-up), sparse (CSR)
    for whole-trajectory fits (thousands of poses) and for many samples (the dense matrix would grow with them)."""
    if shape[1] <= DENSE_FIT_COLUMNS and shape[0] * shape[1] <= DENSE_FIT_CELLS:
        out = np.zeros(shape)
        np.add.at(out, (rows, cols), vals)
        return out
    import scipy.sparse as sp

    return sp.csr_matrix((vals, (rows, cols)), shape=shape)
