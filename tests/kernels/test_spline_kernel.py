"""Taichi SO(3) and spline funcs vs their numpy oracles (ti_cmax.so3, ti_cmax.spline)."""
import functools

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from ti_cmax import so3
from ti_cmax.spline import SO3Spline


@functools.cache
def _so3_kernel(dtype_name):
    from ti_cmax.kernels.runtime import ti
    from ti_cmax.kernels.so3 import so3_funcs

    dtype = ti.f64 if dtype_name == "f64" else ti.f32
    g = so3_funcs(dtype)

    @ti.kernel
    def k(
        v: ti.types.ndarray(dtype=g.vec3, ndim=1),
        out_exp: ti.types.ndarray(dtype=g.mat3, ndim=1),
        out_log: ti.types.ndarray(dtype=g.vec3, ndim=1),
        out_jr: ti.types.ndarray(dtype=g.mat3, ndim=1),
        out_jrinv: ti.types.ndarray(dtype=g.mat3, ndim=1),
    ):
        for i in range(v.shape[0]):
            r = g.exp(v[i])
            out_exp[i] = r
            out_log[i] = g.log(r)
            out_jr[i] = g.jr(v[i])
            out_jrinv[i] = g.jr_inv(v[i])

    return k


def _rotvecs():
    rng = np.random.default_rng(0)
    axes = rng.normal(size=(40, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    angles = np.concatenate([[0.0, 1e-9, 1e-6, 1e-3, 0.05, 0.099, 0.101], rng.uniform(0.1, 3.0, 28),
                             [3.1, 3.13, 3.14, 3.1415, np.pi - 1e-7]])
    return axes * angles[:, None]


@pytest.mark.parametrize("dtype, tol", [(np.float64, 1e-12), (np.float32, 2e-6)])
def test_so3_funcs_match_numpy(ti_runtime, dtype, tol):
    v = _rotvecs().astype(dtype)
    n = len(v)
    out = [np.zeros((n, 3, 3), dtype), np.zeros((n, 3), dtype), np.zeros((n, 3, 3), dtype), np.zeros((n, 3, 3), dtype)]
    _so3_kernel("f64" if dtype == np.float64 else "f32")(v, *out)
    vd = v.astype(np.float64)
    np.testing.assert_allclose(out[0], so3.exp(vd), atol=tol)
    # log: compare rotations (the rotation vector flips sign at exactly pi)
    np.testing.assert_allclose(so3.exp(out[1].astype(np.float64)), so3.exp(vd), atol=10 * tol)
    near_pi = np.linalg.norm(vd, axis=1) > 3.14
    np.testing.assert_allclose(out[1][~near_pi], vd[~near_pi], atol=10 * tol)
    np.testing.assert_allclose(out[2], so3.right_jacobian(vd), atol=tol)
    ok = np.linalg.norm(vd, axis=1) < 3.0  # Jr^-1 is singular at 2 pi and steep near pi
    np.testing.assert_allclose(out[3][ok], so3.right_jacobian_inv(vd[ok]), atol=10 * tol, rtol=10 * tol)


@pytest.mark.parametrize("degree", [1, 3])
@pytest.mark.parametrize("dtype, tol", [(np.float64, 1e-12), (np.float32, 5e-6)])
def test_spline_funcs_match_numpy(ti_runtime, degree, dtype, tol):
    from ti_cmax.kernels.spline import spline_pose_jacobians

    rng = np.random.default_rng(degree)
    m = 9
    steps = rng.normal(size=(m, 3)) * 0.3
    steps[3:5] *= 1e-6  # nearly equal consecutive control poses exercise the small-angle branches
    spline = SO3Spline(degree, 0.0, 0.05, Rotation.from_rotvec(np.cumsum(steps, axis=0)).as_matrix())
    start, end = spline.valid_time_range()
    times = np.concatenate([spline.knot_times()[(degree - 1) // 2 : m - (degree - 1) // 2],
                            rng.uniform(start, end, 40)])
    s, u = spline.support(times)
    first, r_ref, j_ref = spline.jacobians(times)
    r_ti, j_ti = spline_pose_jacobians(degree, spline.control_R, s, u, dtype=dtype)
    np.testing.assert_array_equal(first, s)
    np.testing.assert_allclose(r_ti, r_ref, atol=tol)
    np.testing.assert_allclose(j_ti, j_ref, atol=tol * 10)


@pytest.mark.parametrize("degree", [1, 3])
def test_pose_func_matches_numpy(ti_runtime, degree):
    """pose_from_segments (the pose alone, from the knot intervals' segments) against SO3Spline.evaluate."""
    from ti_cmax.kernels.runtime import ti
    from ti_cmax.kernels.spline import spline_funcs

    f = spline_funcs(ti.f64, degree)
    mat3 = ti.types.matrix(3, 3, ti.f64)
    vec3 = ti.types.vector(3, ti.f64)

    @ti.kernel
    def k(ctrl: ti.types.ndarray(dtype=mat3, ndim=1), s: ti.types.ndarray(dtype=ti.i32, ndim=1),
          u: ti.types.ndarray(dtype=ti.f64, ndim=1), om: ti.types.ndarray(dtype=vec3, ndim=1),
          out: ti.types.ndarray(dtype=mat3, ndim=1)):
        for i in range(1, ctrl.shape[0]):
            om[i], _ = f.segment(ctrl, i)
        for i in range(s.shape[0]):
            out[i] = f.pose_from_segments(ctrl, om, s[i], u[i])

    rng = np.random.default_rng(7)
    spline = SO3Spline(degree, 0.0, 0.05, Rotation.from_rotvec(np.cumsum(rng.normal(size=(6, 3)), 0)).as_matrix())
    times = rng.uniform(*spline.valid_time_range(), 20)
    s, u = spline.support(times)
    out = np.zeros((len(times), 3, 3))
    k(spline.control_R, s.astype(np.int32), u, np.zeros((spline.num_control, 3)), out)
    np.testing.assert_allclose(out, spline.evaluate(times), atol=1e-12)
