"""Shared bilinear vote/sample (kernels/bilinear.py): Taichi funcs vs numpy twins, hand-computed 2x2 case."""
import functools

import numpy as np
import pytest

W, H = 7, 5


@functools.cache
def _test_kernels(dtype):
    from ti_cmax.kernels.bilinear import ADD, ATOMIC, CLEAR, bilinear_funcs
    from ti_cmax.kernels.runtime import ti

    bl = bilinear_funcs(dtype)
    arr1 = ti.types.ndarray(dtype=dtype, ndim=1)
    arr2 = ti.types.ndarray(dtype=dtype, ndim=2)

    @ti.kernel
    def k_vote(u: arr1, v: arr1, w: arr1, wrap: ti.i32, img: arr2, landed: arr1):
        for k in range(u.shape[0]):  # parallel: atomic adds
            if wrap:
                landed[k] = bl.vote_wrap(img, u[k], v[k], w[k], ATOMIC)
            else:
                landed[k] = bl.vote(img, u[k], v[k], w[k], ATOMIC)

    @ti.kernel
    def k_vote_plain_then_clear(u: arr1, v: arr1, img: arr2, cleared: arr2):
        ti.loop_config(serialize=True)
        for k in range(u.shape[0]):
            bl.vote(img, u[k], v[k], 1.0, ADD)
            bl.vote(cleared, u[k], v[k], 1.0, ATOMIC)
        for k in range(u.shape[0]):
            bl.vote(cleared, u[k], v[k], 1.0, CLEAR)

    @ti.kernel
    def k_sample(img: arr2, u: arr1, v: arr1, wrap: ti.i32, out: arr2):
        for k in range(u.shape[0]):
            val, du, dv = ti.cast(0.0, dtype), ti.cast(0.0, dtype), ti.cast(0.0, dtype)
            if wrap:
                i0, j0, fu, fv = bl.split(u[k], v[k])
                ia, ib = bl.wrap_cols(i0, img.shape[1])
                val, du, dv = bl.interp(bl.gather(img, 0, img.shape[0], j0, ia, ib, 1, 1, -1), fu, fv)
            else:
                val, du, dv = bl.sample(img, u[k], v[k])
            out[k, 0] = val
            out[k, 1] = du
            out[k, 2] = dv

    return k_vote, k_vote_plain_then_clear, k_sample


def _points(seed=0, n=400):
    """Random points covering the image and a margin outside, exact integers, and u in [w-1, w) (the seam)."""
    rng = np.random.default_rng(seed)
    u = rng.uniform(-2.5, W + 1.5, n)
    v = rng.uniform(-2.5, H + 1.5, n)
    ints_u = rng.integers(-1, W + 1, 40).astype(float)
    ints_v = rng.integers(-1, H + 1, 40).astype(float)
    seam_u = rng.uniform(W - 1, W, 40)
    seam_v = rng.uniform(0, H - 1, 40)
    return np.concatenate([u, ints_u, seam_u]), np.concatenate([v, ints_v, seam_v])


def _ti_dtype(dtype):
    from ti_cmax.kernels.runtime import ti

    return ti.f64 if dtype == np.float64 else ti.f32


def test_two_by_two_by_hand():
    from ti_cmax.kernels import bilinear

    img = bilinear.vote_numpy(np.zeros((2, 2)), np.array([0.25]), np.array([0.5]), np.array([2.0]))
    np.testing.assert_allclose(img, [[0.75, 0.25], [0.75, 0.25]])
    m = np.array([[1.0, 3.0], [5.0, 11.0]])
    val, du, dv = bilinear.sample_numpy(m, np.array([0.25]), np.array([0.5]))
    # rows: 1 + 0.25 * 2 = 1.5 and 5 + 0.25 * 6 = 6.5; value 4.0; d/du = 0.5 * 2 + 0.5 * 6; d/dv = 6.5 - 1.5
    assert (val[0], du[0], dv[0]) == pytest.approx((4.0, 4.0, 5.0))
    # wrap: u = 1.5 on a 2-wide map splits between column 1 and column 0
    img = bilinear.vote_numpy(np.zeros((2, 2)), np.array([1.5]), np.array([0.0]), wrap_u=True)
    np.testing.assert_allclose(img, [[0.5, 0.5], [0.0, 0.0]])
    img = bilinear.vote_numpy(np.zeros((2, 2)), np.array([1.5]), np.array([0.0]))
    np.testing.assert_allclose(img, [[0.0, 0.5], [0.0, 0.0]])


@pytest.mark.parametrize("dtype,tol", [(np.float64, 1e-12), (np.float32, 2e-5)])
@pytest.mark.parametrize("wrap", [False, True])
def test_vote_matches_numpy(ti_runtime, dtype, tol, wrap):
    from ti_cmax.kernels import bilinear

    u, v = _points()
    if wrap:
        u = np.clip(u, -W + 0.5, 2 * W - 0.5)
    w = np.random.default_rng(1).uniform(0.5, 2.0, len(u))
    img = np.zeros((H, W), dtype)
    landed = np.zeros(len(u), dtype)
    k_vote = _test_kernels(_ti_dtype(dtype))[0]
    k_vote(u.astype(dtype), v.astype(dtype), w.astype(dtype), int(wrap), img, landed)
    ref = bilinear.vote_numpy(np.zeros((H, W)), u, v, w, wrap_u=wrap)
    np.testing.assert_allclose(img, ref, atol=tol * len(u))
    # the landed weight is what the image gained from each point
    per_point = [bilinear.vote_numpy(np.zeros((H, W)), u[k:k + 1], v[k:k + 1], w[k:k + 1], wrap_u=wrap).sum()
                 for k in range(len(u))]
    np.testing.assert_allclose(landed, per_point, atol=10 * tol)
    assert 0 < img.sum() < w.sum()  # some points fall (partly) outside


def test_plain_vote_and_clear(ti_runtime):
    from ti_cmax.kernels import bilinear
    from ti_cmax.kernels.runtime import ti

    u, v = _points(seed=2)
    img = np.zeros((H, W))
    cleared = np.full((H, W), 0.0)
    _test_kernels(ti.f64)[1](u, v, img, cleared)
    np.testing.assert_allclose(img, bilinear.vote_numpy(np.zeros((H, W)), u, v), atol=1e-12)
    assert not cleared.any()


@pytest.mark.parametrize("dtype,tol", [(np.float64, 1e-12), (np.float32, 1e-5)])
@pytest.mark.parametrize("wrap", [False, True])
def test_sample_matches_numpy(ti_runtime, dtype, tol, wrap):
    from ti_cmax.kernels import bilinear

    u, v = _points(seed=3)
    if wrap:
        u = np.clip(u, -W + 0.5, 2 * W - 0.5)
    img = np.random.default_rng(4).uniform(-1, 1, (H, W))
    out = np.zeros((len(u), 3), dtype)
    _test_kernels(_ti_dtype(dtype))[2](img.astype(dtype), u.astype(dtype), v.astype(dtype), int(wrap), out)
    val, du, dv = bilinear.sample_numpy(img, u, v, wrap_u=wrap)
    np.testing.assert_allclose(out, np.stack([val, du, dv], 1), atol=tol)
    # the derivatives are those of the interpolant (central differences away from pixel edges)
    eps = 1e-6
    inner = (np.abs(u - np.round(u)) > 1e-3) & (np.abs(v - np.round(v)) > 1e-3)
    fd_u = (bilinear.sample_numpy(img, u + eps, v, wrap)[0] - bilinear.sample_numpy(img, u - eps, v, wrap)[0]) / 2e-6
    fd_v = (bilinear.sample_numpy(img, u, v + eps, wrap)[0] - bilinear.sample_numpy(img, u, v - eps, wrap)[0]) / 2e-6
    np.testing.assert_allclose(du[inner], fd_u[inner], atol=1e-6)
    np.testing.assert_allclose(dv[inner], fd_v[inner], atol=1e-6)


def test_sample_channels_and_clamp():
    from ti_cmax.kernels import bilinear

    rng = np.random.default_rng(5)
    img = rng.uniform(size=(H, W, 3))
    u, v = _points(seed=6, n=50)
    val, du, dv = bilinear.sample_numpy(img, u, v, wrap_u=True)
    for c in range(3):
        ref = bilinear.sample_numpy(img[..., c], u, v, wrap_u=True)
        np.testing.assert_allclose((val[:, c], du[:, c], dv[:, c]), ref, atol=1e-14)
    # clamp_v: rows beyond the border read the border row
    val, _, _ = bilinear.sample_numpy(img[..., 0], np.array([2.0]), np.array([-3.0]), wrap_u=True, clamp_v=True)
    assert val[0] == pytest.approx(img[0, 2, 0])


def test_wrapped_vote_far_outside_the_seam_range(ti_runtime):
    """Columns beyond [-w, 2w) (a diverged pose) still wrap into the image instead of indexing outside it."""
    from ti_cmax.kernels import bilinear
    from ti_cmax.kernels.runtime import ti

    u = np.array([5.5 * W + 0.25, -3.0 * W - 0.75, 1e6 + 0.5, -1e6 - 0.25])
    v = np.array([1.5, 2.25, 0.5, 3.0])
    img = np.zeros((H, W))
    landed = np.zeros(len(u))
    _test_kernels(ti.f64)[0](u, v, np.ones(len(u)), 1, img, landed)
    np.testing.assert_allclose(img, bilinear.vote_numpy(np.zeros((H, W)), u, v, wrap_u=True), atol=1e-9)
    np.testing.assert_allclose(landed, 1.0)
