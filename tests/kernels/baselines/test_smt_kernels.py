"""SMT tracker kernels (kernels/baselines/smt.py): Taichi vs numpy twins (f64, f32), reference selection rules, Jacobian vs
central differences, the iterated EKF update vs its information form."""
import numpy as np
import pytest

from ti_cmax import so3
from ti_cmax.camera import Camera
from ti_cmax.kernels.baselines import smt as ks

W, H = 256, 128
C, SIGMA, OUTLIER, MIN_DISP, HUBER, FLOOR = 0.2, 0.1, 10.0, 1.0, 2.0, 0.05
BS = 100


@pytest.fixture(scope="module")
def scene():
    """Random smooth gradient map with covariances and a partly mapped area; a 40x30 camera turning at ~13 rad/s (0.5 map px per batch)
    (batches 1 ms apart) with 200 random events per batch on 60 pixels (several events per pixel and batch)."""
    rng = np.random.default_rng(0)
    vv, uu = np.mgrid[0:H, 0:W]
    grad = np.stack([0.3 * np.sin(uu / 7.0) * np.cos(vv / 5.0), 0.2 * np.cos(uu / 4.0 + vv / 9.0)], -1)
    cov = np.zeros((H, W, 3))
    cov[..., 0] = 0.01 + 0.05 * rng.random((H, W))
    cov[..., 2] = 0.01 + 0.05 * rng.random((H, W))
    cov[..., 1] = 0.3 * np.sqrt(cov[..., 0] * cov[..., 2]) * rng.uniform(-1, 1, (H, W))
    updates = (rng.random((H, W)) < 0.7).astype(np.int32) * 3
    cam = Camera.ideal(40, 30, 60.0)
    nb = 12
    pixels = rng.choice(40 * 30, 60, replace=False)
    pix = np.concatenate([np.zeros(BS, np.int64), rng.choice(pixels, (nb - 1) * BS)]).astype(np.int32)
    bearings = cam.bearing_lut.astype(np.float64)[pix]
    pol = rng.choice(np.array([-1, 1], np.int8), nb * BS, p=[0.1, 0.9])
    omega = np.array([2.0, 12.0, -4.0])
    hist = so3.exp(np.outer(np.arange(nb) * 1e-3, omega) + rng.normal(scale=2e-4, size=(nb, 3)))
    return dict(grad=grad, cov=cov, updates=updates, bearings=bearings, pix=pix, pol=pol, hist=hist, nb=nb,
                R=hist[-1], omega=omega)


def _selected(s, dtype, impl="taichi", b1=None):
    """References of batches 1..b1-1 (default: all) under the history poses themselves."""
    n = len(s["pol"])
    b1 = b1 or s["nb"]
    state = ks.new_reference_state(40 * 30)
    uv, cnt = np.zeros((n, 2), dtype), np.zeros(n, np.int32)
    hist = np.ascontiguousarray(s["hist"], dtype)
    args = (hist, hist[1:b1], 1, b1, BS, np.ascontiguousarray(s["bearings"], dtype), s["pix"], s["pol"], state, W, H,
            OUTLIER, MIN_DISP, 90.0, uv, cnt)
    (ks.select_references_numpy if impl == "numpy" else ks.select_references)(*args)
    return uv, cnt, state


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_select_references_matches_numpy(ti_runtime, scene, dtype):
    uv, cnt, st = _selected(scene, dtype)
    uv_r, cnt_r, st_r = _selected(scene, np.float64, "numpy")
    ok = cnt_r > 0
    assert ok.sum() > 100 and cnt_r.max() >= 2  # segments of several events exist
    if dtype == np.float64:
        np.testing.assert_array_equal(cnt, cnt_r)
        for k in st:
            np.testing.assert_array_equal(st[k], st_r[k])
    else:  # f32 projections may move a few segments across the 1 px gate
        assert np.mean(cnt == cnt_r) > 0.97
    both = ok & (cnt > 0)
    np.testing.assert_allclose(uv[both], uv_r[both], atol=1e-3 if dtype == np.float32 else 1e-9)


def test_selection_rules(ti_runtime):
    """One pixel panning 0.4 map px per batch: references every 3rd batch with n = 3 same-polarity events; a
    polarity change restarts the segment at the previous event; a jump beyond the outlier distance resets."""
    cam = Camera.ideal(8, 6, 10.0)
    b = cam.bearing_lut[20:21].astype(np.float64)
    step = 0.4 * 2 * np.pi / W
    nb = 9
    hist = so3.exp(np.outer(np.arange(nb) * step, [0.0, 1.0, 0.0]))
    hist[8] = so3.exp(np.array([0.0, 1.0, 0.0]) * 40 * step) @ hist[7]  # 16 px jump
    pol = np.array([0, 1, 1, 1, 1, 1, 1, -1, -1], np.int8)  # one event per batch; batch 0 is padding
    pix = np.full(nb, 20, np.int32)
    state = ks.new_reference_state(48)
    uv, cnt = np.zeros((nb, 2)), np.zeros(nb, np.int32)
    ks.select_references_numpy(hist, hist[1:], 1, nb, 1, np.repeat(b, nb, 0), pix, pol, state, W, H, OUTLIER, 1.0,
                               90.0, uv, cnt)
    # batch 1: first event (reference); 2: 0.4 px, 3: 0.8 px (accumulate); 4: 1.2 px -> n = 3, reference := 4;
    # 5, 6: accumulate; 7: polarity change -> reference := 6, 0.4 px; 8: 16.4 px -> outlier, reference := 8
    np.testing.assert_array_equal(cnt, [0, 0, 0, 0, 3, 0, 0, 0, 0])
    assert state["ref_b"][20] == 8 and state["count"][20] == 0 and state["last_p"][20] == -1
    ref_u = ks.equirect_numpy((hist[1] @ b[0])[None], W, H)[0][0]
    assert abs(uv[4, 0] - ref_u) < 1e-9
    # the pixel looks 0.63 deg off the equator: with a 0.5 deg latitude band nothing is measured
    cnt[:] = 0
    ks.select_references_numpy(hist, hist[1:], 1, nb, 1, np.repeat(b, nb, 0), pix, pol, ks.new_reference_state(48), W,
                               H, OUTLIER, 1.0, 0.5, uv, cnt)
    assert not cnt.any()


def _batch_args(s, dtype, b):
    uv, cnt, _ = _selected(s, np.float64, "numpy")
    e0, e1 = b * BS, (b + 1) * BS
    return (s["bearings"][e0:e1].astype(dtype), uv[e0:e1].astype(dtype), cnt[e0:e1], s["pol"][e0:e1],
            s["grad"].astype(dtype), s["cov"].astype(dtype), s["updates"])


@pytest.mark.parametrize("pos_var", [0.0, 1.0 / 6.0])
@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_ekf_accumulate_matches_numpy(ti_runtime, scene, dtype, pos_var):
    b = scene["nb"] - 1
    ref = ks.ekf_accumulate_numpy(scene["R"], *_batch_args(scene, np.float64, b), C, SIGMA, HUBER, pos_var)
    out = ks.ekf_accumulate(scene["R"], *_batch_args(scene, dtype, b), C, SIGMA, HUBER, pos_var)
    if pos_var:  # the crossing-position variance |g|^2 pos_var is in S: less information than without it
        base = ks.ekf_accumulate_numpy(scene["R"], *_batch_args(scene, np.float64, b), C, SIGMA, HUBER)
        assert ref[0] + ref[3] + ref[5] < base[0] + base[3] + base[5]
    assert ref[9] > 15 and ref[10] > 8  # enough valid and supported measurements to mean something
    if dtype == np.float64:
        np.testing.assert_allclose(out, ref, rtol=1e-8, atol=1e-9)
    else:
        np.testing.assert_array_equal(out[9:11], ref[9:11])
        np.testing.assert_allclose(out[:9], ref[:9], atol=0.02 * np.abs(ref[:9]).max())


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_pf_loglik_matches_numpy(ti_runtime, scene, dtype):
    rng = np.random.default_rng(1)
    parts = so3.exp(rng.normal(scale=0.003, size=(7, 3))) @ scene["R"]
    b = scene["nb"] - 1
    ref = ks.pf_loglik_numpy(parts, *_batch_args(scene, np.float64, b), C, SIGMA, FLOOR, 1.0 / 6.0)
    out = ks.pf_loglik(parts, *_batch_args(scene, dtype, b), C, SIGMA, FLOOR, 1.0 / 6.0)
    if dtype == np.float64:
        np.testing.assert_allclose(out, ref, rtol=1e-9)
    else:
        np.testing.assert_allclose(out, ref, rtol=2e-2, atol=2.0)
    assert np.argmax(out) == np.argmax(ref) or abs(out.max() - ref[np.argmax(out)]) < 2.0


def test_measurement_jacobian_central_differences(scene):
    """H = d z_hat / d delta (left perturbation) of the numpy model, float64, vs central differences."""
    b = scene["nb"] - 1
    bear, uv, cnt, pol, grad, cov, upd = _batch_args(scene, np.float64, b)
    ok, _, _, Hj, _, _ = ks._measure_numpy(scene["R"], bear, uv, cnt, pol, grad, cov, upd, C, SIGMA ** 2)
    eps = 1e-7
    num = np.zeros_like(Hj)
    for a in range(3):
        d = np.zeros(3)
        d[a] = eps
        zp = ks._measure_numpy(so3.exp(d) @ scene["R"], bear, uv, cnt, pol, grad, cov, upd, C, SIGMA ** 2)[4]
        zm = ks._measure_numpy(so3.exp(-d) @ scene["R"], bear, uv, cnt, pol, grad, cov, upd, C, SIGMA ** 2)[4]
        num[:, a] = (zp - zm) / (2 * eps)
    err = np.abs(num[ok] - Hj[ok])
    # bilinear g is piecewise linear: a perturbation may straddle a pixel border for a few events
    assert np.median(err) < 1e-5 * (np.abs(Hj[ok]).max() + 1)
    assert np.mean(err < 1e-4 * (np.abs(Hj[ok]).max() + 1)) > 0.95


def test_iterated_update_equals_information_form(scene):
    """x = P[:, d] (I + Lam P_dd)^-1 (b + Lam d) is the Gauss-Newton step (P^-1 + E Lam E^T)^-1 E (b + Lam d)."""
    rng = np.random.default_rng(3)
    a = rng.normal(size=(6, 6))
    P = a @ a.T * 1e-4 + np.eye(6) * 1e-6
    h = rng.normal(size=(40, 3)) * 100
    lam, bvec, d = h.T @ h, rng.normal(size=3), rng.normal(size=3) * 1e-3
    x = P[:, :3] @ np.linalg.solve(np.eye(3) + lam @ P[:3, :3], bvec + lam @ d)
    info = np.linalg.inv(P)
    info[:3, :3] += lam
    np.testing.assert_allclose(x, np.linalg.solve(info, np.concatenate([bvec + lam @ d, np.zeros(3)])), rtol=1e-8)


@pytest.mark.slow
@pytest.mark.parametrize("model", ["pose", "velocity", "acceleration"])
@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_ekf_track_matches_numpy(ti_runtime, scene, dtype, model):
    """References selected over batches 1..8 under the history poses, then EKF-SMT (two iterations; constant
    velocity with pose or state references, or constant acceleration) on batches 9..11 from the pose of batch 8."""
    velocity_reference = model != "pose"
    ns = 9 if model == "acceleration" else 6
    nb, b_track = scene["nb"], 9
    out = {}
    for impl in ("numpy", "taichi"):
        dt_ = np.float64 if impl == "numpy" else dtype
        uv, cnt, state = _selected(scene, dt_, impl, b1=b_track)
        h64 = scene["hist"].copy()
        h = np.ascontiguousarray(h64, dt_)
        sR, sw = h64[b_track - 1][None].copy(), scene["omega"][None] * 0.9
        sP = np.diag([1e-7] * 3 + [0.1] * 3 + [100.0] * (ns - 6))[None].copy()
        sa = np.array([[30.0, -20.0, 10.0]]) if ns == 9 else None
        fn = ks.ekf_track_numpy if impl == "numpy" else ks.ekf_track
        diag = fn(h if impl == "taichi" else h64, h64, np.arange(nb) * 1e-3, b_track, nb, BS,
                  np.ascontiguousarray(scene["bearings"], dt_), scene["pix"], scene["pol"], state, uv, cnt,
                  scene["grad"].astype(dt_), scene["cov"].astype(dt_), scene["updates"], C, SIGMA, OUTLIER, MIN_DISP,
                  90.0, HUBER, 0.0, 0.0, 20.0, 2, sR, sw, sP, velocity_reference, np.zeros(len(cnt), np.int32),
                  state_a=sa, q_jerk=1000.0, position_var=1.0 / 6.0)
        out[impl] = (h64[b_track:].copy(), diag, sP[0].copy(), sw[0].copy(), None if sa is None else sa[0].copy())
    tol = 1e-9 if dtype == np.float64 else 2e-4
    rt = 1e-6 if dtype == np.float64 else 0.05
    assert np.all(so3.geodesic_angle(out["numpy"][0], out["taichi"][0]) < tol)
    assert out["numpy"][1][:, 0].min() > 5  # measurements in every batch
    np.testing.assert_allclose(out["taichi"][1][:, 3], out["numpy"][1][:, 3], rtol=1e-6 if dtype == np.float64 else 0.05)
    np.testing.assert_allclose(out["taichi"][3], out["numpy"][3], rtol=rt)
    np.testing.assert_allclose(out["taichi"][2], out["numpy"][2], rtol=1e-6 if dtype == np.float64 else 0.05,
                               atol=1e-12)
    assert not np.allclose(out["numpy"][3], scene["omega"] * 0.9)  # the update moved the velocity
    if ns == 9:  # and the acceleration
        np.testing.assert_allclose(out["taichi"][4], out["numpy"][4], rtol=1e-6 if dtype == np.float64 else 0.05,
                                   atol=1e-6 if dtype == np.float64 else 0.5)
        assert not np.allclose(out["numpy"][4], [30.0, -20.0, 10.0])
    if dtype == np.float64:
        np.testing.assert_array_equal(out["taichi"][1][:, :3], out["numpy"][1][:, :3])
        if velocity_reference:  # the innovation-consistency statistic (numerator, denominator > 0)
            np.testing.assert_allclose(out["taichi"][1][:, 5:7], out["numpy"][1][:, 5:7], rtol=1e-6, atol=1e-9)
            assert np.all(out["numpy"][1][:, 6] > 0)


@pytest.mark.parametrize("accel", [None, [300.0, -200.0, 100.0]])
def test_velocity_reference_jacobians_central_differences(scene, accel):
    """H_d (left pose perturbation), H_w (camera-frame angular velocity) and, with an angular acceleration a, H_a =
    -(dt_ref / 2) H_w of the state-referenced model, float64, vs central differences."""
    b = scene["nb"] - 1
    bear, uv, cnt, pol, grad, cov, upd = _batch_args(scene, np.float64, b)
    dtr = np.random.default_rng(4).uniform(1e-3, 5e-3, len(pol))
    R, w = scene["R"], scene["omega"]
    a = None if accel is None else np.array(accel)

    def z(R_, w_, a_=a):
        return ks._measure_cv_numpy(R_, w_, dtr, bear, cnt, pol, grad, cov, upd, C, SIGMA ** 2, 3.0, a_, 50.0)[5]

    ok, _, _, Hd, Hw, _, _ = ks._measure_cv_numpy(R, w, dtr, bear, cnt, pol, grad, cov, upd, C, SIGMA ** 2, 3.0, a,
                                                  50.0)
    assert ok.sum() > 15
    eps = 1e-7
    checks = [(Hd, lambda d: z(so3.exp(d) @ R, w)), (Hw, lambda d: z(R, w + d))]
    if a is not None:
        checks.append((-0.5 * dtr[:, None] * Hw, lambda d: z(R, w, a + d * 1e3)))  # step 1e-4 rad/s^2
    for k, (Hj, f) in enumerate(checks):
        if k == 2:
            Hj = Hj * 1e3
        num = np.zeros_like(Hj)
        for i in range(3):
            d = np.zeros(3)
            d[i] = eps
            num[:, i] = (f(d) - f(-d)) / (2 * eps)
        err = np.abs(num[ok] - Hj[ok])
        assert np.median(err) < 1e-5 * np.abs(Hj[ok]).max()
        assert np.mean(err < 1e-4 * np.abs(Hj[ok]).max()) > 0.95
