"""SMT tracker kernels (kernels/smt.py): Taichi vs numpy twins (f64, f32), Jacobian vs central differences."""
import numpy as np
import pytest

from ti_cmax import so3
from ti_cmax.camera import Camera
from ti_cmax.kernels import smt as ks

W, H = 256, 128
C, SIGMA, OUTLIER, MIN_DISP, HUBER, FLOOR = 0.2, 0.1, 10.0, 0.05, 2.0, 0.05


@pytest.fixture(scope="module")
def scene():
    """Random smooth gradient map with covariances and a partly mapped area; events of a 40x30 camera whose
    previous events happened at poses a few mrad away."""
    rng = np.random.default_rng(0)
    vv, uu = np.mgrid[0:H, 0:W]
    grad = np.stack([0.3 * np.sin(uu / 7.0) * np.cos(vv / 5.0), 0.2 * np.cos(uu / 4.0 + vv / 9.0)], -1)
    cov = np.zeros((H, W, 3))
    cov[..., 0] = 0.01 + 0.05 * rng.random((H, W))
    cov[..., 2] = 0.01 + 0.05 * rng.random((H, W))
    cov[..., 1] = 0.3 * np.sqrt(cov[..., 0] * cov[..., 2]) * rng.uniform(-1, 1, (H, W))
    updates = (rng.random((H, W)) < 0.7).astype(np.int32) * 3
    cam = Camera.ideal(40, 30, 60.0)
    n = 300
    x, y = rng.integers(0, 40, n), rng.integers(0, 30, n)
    bearings = cam.bearings(x, y, dtype=np.float64)
    pol = rng.choice(np.array([-1, 1], np.int8), n)
    poses = so3.exp(rng.normal(scale=0.01, size=(6, 3)))
    prev_idx = rng.integers(-1, 6, n).astype(np.int32)
    R = so3.exp(np.array([0.004, -0.003, 0.002]))
    return dict(grad=grad, cov=cov, updates=updates, bearings=bearings, pol=pol, poses=poses, prev_idx=prev_idx, R=R)


def _args(s, dtype):
    uv = np.nan_to_num(ks.project_prev_numpy(s["poses"], s["prev_idx"], s["bearings"], W, H))
    return (s["bearings"].astype(dtype), uv.astype(dtype), (s["prev_idx"] >= 0).astype(np.int8), s["pol"],
            s["grad"].astype(dtype), s["cov"].astype(dtype), s["updates"])


@pytest.mark.parametrize("dtype,rtol", [(np.float64, 1e-9), (np.float32, 2e-3)])
def test_project_prev_matches_numpy(ti_runtime, scene, dtype, rtol):
    ref = ks.project_prev_numpy(scene["poses"], scene["prev_idx"], scene["bearings"], W, H)
    out = ks.project_prev(scene["poses"], scene["prev_idx"], scene["bearings"], W, H, dtype)
    ok = scene["prev_idx"] >= 0
    np.testing.assert_allclose(out[ok], ref[ok], rtol=0, atol=rtol * W)
    assert np.all(out[~ok] == 0)


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_ekf_accumulate_matches_numpy(ti_runtime, scene, dtype):
    args = _args(scene, dtype)
    ref = ks.ekf_accumulate_numpy(scene["R"], *_args(scene, np.float64), C, SIGMA, OUTLIER, MIN_DISP, HUBER)
    out = ks.ekf_accumulate(scene["R"], *args, C, SIGMA, OUTLIER, MIN_DISP, HUBER)
    assert ref[9] > 100 and ref[10] > 50  # enough valid and supported measurements to mean something
    if dtype == np.float64:
        np.testing.assert_allclose(out, ref, rtol=1e-8, atol=1e-9)
    else:  # f32 projections may move a few events across the gates and pixel borders
        assert np.all(np.abs(out[9:12] - ref[9:12]) <= 2)
        np.testing.assert_allclose(out[:9], ref[:9], atol=0.05 * np.abs(ref[:9]).max())


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_pf_loglik_matches_numpy(ti_runtime, scene, dtype):
    rng = np.random.default_rng(1)
    parts = so3.exp(rng.normal(scale=0.003, size=(7, 3))) @ scene["R"]
    ref = ks.pf_loglik_numpy(parts, *_args(scene, np.float64), C, SIGMA, OUTLIER, MIN_DISP, FLOOR)
    out = ks.pf_loglik(parts, *_args(scene, dtype), C, SIGMA, OUTLIER, MIN_DISP, FLOOR)
    if dtype == np.float64:
        np.testing.assert_allclose(out, ref, rtol=1e-9)
    else:
        np.testing.assert_allclose(out, ref, rtol=2e-2, atol=2.0)
    assert np.argmax(out) == np.argmax(ref) or abs(out.max() - ref[np.argmax(out)]) < 2.0


def test_measurement_jacobian_central_differences(scene):
    """H = d z_hat / d delta (left perturbation) of the numpy model, float64, vs central differences."""
    bear, uv, valid, pol, grad, cov, upd = _args(scene, np.float64)
    ok, _, _, Hj, _, _ = ks._measure_numpy(scene["R"], bear, uv, valid, pol, grad, cov, upd, C, SIGMA ** 2, OUTLIER,
                                           MIN_DISP)
    eps = 1e-7
    num = np.zeros_like(Hj)
    for a in range(3):
        d = np.zeros(3)
        d[a] = eps
        zp = ks._measure_numpy(so3.exp(d) @ scene["R"], bear, uv, valid, pol, grad, cov, upd, C, SIGMA ** 2,
                               OUTLIER, MIN_DISP)[4]
        zm = ks._measure_numpy(so3.exp(-d) @ scene["R"], bear, uv, valid, pol, grad, cov, upd, C, SIGMA ** 2,
                               OUTLIER, MIN_DISP)[4]
        num[:, a] = (zp - zm) / (2 * eps)
    sel = ok
    err = np.abs(num[sel] - Hj[sel])
    # bilinear g is piecewise linear: a perturbation may straddle a pixel border for a few events
    assert np.median(err) < 1e-5 * (np.abs(Hj[sel]).max() + 1)
    assert np.mean(err < 1e-4 * (np.abs(Hj[sel]).max() + 1)) > 0.95


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_ekf_track_matches_numpy(ti_runtime, scene, dtype):
    """Three batches of 100 events, previous events at the six history poses, two EKF iterations."""
    rng = np.random.default_rng(2)
    n, bs = 300, 100
    nb_hist = 6
    hist64 = np.concatenate([scene["poses"], np.zeros((3, 3, 3))])
    prev_batch = scene["prev_idx"].astype(np.int32)  # the events form batches 6, 7, 8 (indices 600..899)
    bear = np.zeros(((nb_hist + 3) * bs, 3))
    bear[nb_hist * bs:] = scene["bearings"]
    pb = np.full((nb_hist + 3) * bs, -1, np.int32)
    pb[nb_hist * bs:] = prev_batch
    pol = np.ones((nb_hist + 3) * bs, np.int8)
    pol[nb_hist * bs:] = scene["pol"]
    mids = np.arange(nb_hist + 3) * 1e-4
    out = {}
    for impl in ("numpy", "taichi"):
        h64 = hist64.copy()
        h = h64.astype(dtype)
        sR = scene["R"][None].copy()
        sP = (np.eye(3) * 1e-5)[None].copy()
        fn = ks.ekf_track_numpy if impl == "numpy" else ks.ekf_track
        hh = h64 if impl == "numpy" else h
        g, c = scene["grad"].astype(dtype if impl == "taichi" else np.float64), scene["cov"].astype(
            dtype if impl == "taichi" else np.float64)
        diag = fn(hh, h64, mids, nb_hist, nb_hist + 3, bs, np.ascontiguousarray(bear.astype(hh.dtype)), pb, pol, g,
                  c, scene["updates"], C, SIGMA, OUTLIER, MIN_DISP, HUBER, 4.0, 2e-4, 2, sR, sP)
        out[impl] = (h64[nb_hist:].copy(), diag, sP[0].copy())
    ang = so3.geodesic_angle(out["numpy"][0], out["taichi"][0])
    assert np.all(ang < (1e-9 if dtype == np.float64 else 2e-4))
    assert not np.allclose(out["numpy"][0][-1], scene["R"], atol=1e-6)  # the update moved the pose
    np.testing.assert_allclose(out["taichi"][1][:, 3], out["numpy"][1][:, 3],
                               rtol=1e-6 if dtype == np.float64 else 0.05)
    if dtype == np.float64:
        np.testing.assert_array_equal(out["taichi"][1][:, :3], out["numpy"][1][:, :3])
