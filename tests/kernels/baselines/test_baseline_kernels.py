"""RTPT and CMax-GAE kernels vs their numpy twins; analytic derivatives vs central differences (float64)."""
import numpy as np
import pytest

from ti_cmax import so3
from ti_cmax.kernels.baselines import gae, rtpt


@pytest.fixture(scope="module")
def rtpt_problem(ti_runtime):
    rng = np.random.default_rng(0)
    h, w = 64, 128
    O = rng.random((h, w)) * 3
    N = np.floor(rng.random((h, w)) * 4)
    b = np.c_[rng.uniform(-0.5, 0.5, (300, 2)), np.ones(300)]
    R = so3.exp(np.array([0.05, -0.1, 0.02]))
    return b, R, O, N


@pytest.mark.parametrize("dtype,tol", [(np.float32, 1e-4), (np.float64, 1e-12)])
def test_rtpt_normal_equations_match_twin(rtpt_problem, dtype, tol):
    b, R, O, N = rtpt_problem
    c, A, g, q = rtpt.normal_equations_numpy(b, R, O, N)
    c2, A2, g2, q2 = rtpt.normal_equations(b, R, O.astype(dtype), N.astype(dtype), dtype=dtype)
    assert c2 == pytest.approx(c, rel=tol)
    assert np.abs(A2 - A).max() <= tol * np.abs(A).max()
    assert np.abs(g2 - g).max() <= 10 * tol * np.abs(g).max()
    assert q2 == pytest.approx(q, rel=tol)


def test_rtpt_gradient_matches_central_differences(rtpt_problem):
    """J^T r is the gradient of 1/2 sum r^2 w.r.t. the right perturbation R exp(delta) (float64 Taichi path)."""
    b, R, O, N = rtpt_problem
    _, _, g, _ = rtpt.normal_equations(b, R, O, N, dtype=np.float64)
    eps = 1e-6
    fd = np.zeros(3)
    for i in range(3):
        d = np.zeros(3)
        d[i] = eps
        fd[i] = (rtpt.normal_equations(b, R @ so3.exp(d), O, N, dtype=np.float64)[0]
                 - rtpt.normal_equations(b, R @ so3.exp(-d), O, N, dtype=np.float64)[0]) / (2 * eps)
    np.testing.assert_allclose(g, fd, rtol=1e-5, atol=1e-6 * np.abs(fd).max())


def test_rtpt_track_and_map_update_match_twins(rtpt_problem):
    b, R, O, N = rtpt_problem
    r_np, c0, c1, q = rtpt.track_numpy(b, R, O, N, 10, 100.0, 0.4)
    r_ti, d0, d1, q2 = rtpt.track(b, R, O.copy(), N.copy(), 10, 100.0, 0.4, dtype=np.float64)
    assert so3.geodesic_angle(r_np, r_ti) < 1e-10 and d1 == pytest.approx(c1, rel=1e-10)
    K = np.array([[100.0, 0, 60], [0, 100.0, 45], [0, 0, 1]])
    o_np, n_np = rtpt.update_map_numpy(b, R, O, N, K, 120, 90)
    o_ti, n_ti = O.copy(), N.copy()
    rtpt.update_map(b, R, o_ti, n_ti, K, 120, 90, rtpt.footprint_bbox(R, rtpt.view_border_rays(K, 120, 90), 128, 64),
                    dtype=np.float64)
    np.testing.assert_allclose(o_ti, o_np, atol=1e-12)
    np.testing.assert_array_equal(n_ti, n_np)  # the bounding box covers the whole footprint
    assert (n_ti - N).sum() > 0


@pytest.mark.slow
def test_rtpt_gauss_newton_reduces_eq4_on_simulated_packet(ti_runtime):
    """A map built from the true poses; a packet tracked from a 1 deg perturbed start: cost down, rotation back."""
    from ti_cmax.simulate import SimulatorConfig, simulate_sequence

    seq = simulate_sequence(SimulatorConfig(scene="bay", sensor="DVS128", duration=0.4, max_angular_velocity=1.5,
                                            seed=2))
    cam, ev = seq.camera, seq.events
    h, w = 256, 512
    O = np.zeros((h, w), np.float32)
    N = np.zeros((h, w), np.float32)
    rays = rtpt.view_border_rays(cam.K, cam.width, cam.height)
    n = 1500
    npk = len(ev) // n
    for i in range(npk - 1):
        sl = slice(i * n, (i + 1) * n)
        r = seq.groundtruth.at(0.5 * (ev.t[sl.start] + ev.t[sl.stop - 1]))[0]
        rtpt.update_map(cam.bearings(ev.x[sl], ev.y[sl]), r, O, N, cam.K, cam.width, cam.height,
                        rtpt.footprint_bbox(r, rays, w, h))
    sl = slice((npk - 1) * n, npk * n)
    b = cam.bearings(ev.x[sl], ev.y[sl])
    r_true = seq.groundtruth.at(0.5 * (ev.t[sl.start] + ev.t[sl.stop - 1]))[0]
    r0 = r_true @ so3.exp(np.radians([0.6, -0.5, 0.3]))
    cost0 = rtpt.normal_equations(b, r0, O, N)[0]
    cost_true = rtpt.normal_equations(b, r_true, O, N)[0]
    _, A, g, _ = rtpt.normal_equations(b, r0, O, N)
    one_step = r0 @ so3.exp(-np.linalg.solve(A + 100.0 * np.eye(3), g))
    assert rtpt.normal_equations(b, one_step, O, N)[0] < cost0  # one damped Gauss-Newton step
    r_est, c0, c1, _ = rtpt.track(b, r0, O, N, 10, 100.0, 0.4)
    assert c1 < c0 and c0 == pytest.approx(cost0, rel=1e-5)
    assert c1 <= 1.02 * cost_true
    assert np.degrees(so3.geodesic_angle(r_est, r_true)) < 0.3


@pytest.fixture(scope="module")
def gae_problem(ti_runtime):
    rng = np.random.default_rng(1)
    W, H = 60, 40
    kv = gae.view_K(np.array([[50.0, 0, 30], [0, 50.0, 20], [0, 0, 1]]), W, H)
    n = 500
    b = np.c_[rng.uniform(-0.6, 0.6, (n, 2)), np.ones(n)]
    dts = rng.uniform(-0.0125, 0.0125, n)
    G = rng.random((2 * H, 2 * W))
    return b, dts, kv, 2 * W, 2 * H, G


@pytest.mark.parametrize("dtype,tol", [(np.float32, 1e-4), (np.float64, 1e-12)])
def test_gae_objective_matches_twin(gae_problem, dtype, tol):
    b, dts, kv, vw, vh, G = gae_problem
    om, ph = np.array([0.5, -1.0, 0.3]), np.array([0.01, 0.02, -0.01])
    c, g, _ = gae.objective_numpy(b, dts, om, ph, kv, vw, vh, G)
    obj = gae.GAEObjective(kv, vw, vh, dtype=dtype)
    obj.set_interval(b, dts, G)
    for _ in range(2):  # the scratch image is cleared between evaluations
        c2, g2 = obj.evaluate(om, ph)
        assert c2 == pytest.approx(c, rel=tol)
        assert np.abs(g2 - g).max() <= tol * np.abs(g).max()


def test_gae_gradient_matches_central_differences(gae_problem):
    b, dts, kv, vw, vh, G = gae_problem
    obj = gae.GAEObjective(kv, vw, vh, dtype=np.float64)
    obj.set_interval(b, dts, G)
    x = np.array([0.5, -1.0, 0.3, 0.01, 0.02, -0.01])
    _, g = obj.evaluate(x[:3], x[3:])
    fd = np.zeros(6)
    eps = 1e-7
    for i in range(6):
        d = np.zeros(6)
        d[i] = eps
        fd[i] = (obj.evaluate((x + d)[:3], (x + d)[3:])[0] - obj.evaluate((x - d)[:3], (x - d)[3:])[0]) / (2 * eps)
    np.testing.assert_allclose(g, fd, rtol=1e-4, atol=1e-6 * np.abs(fd).max())


def test_gae_sphere_render_matches_twin(ti_runtime):
    rng = np.random.default_rng(2)
    hist = np.zeros((64, 128), np.float32)
    hist[rng.integers(0, 64, 500), rng.integers(0, 128, 500)] = rng.random(500)
    kv = gae.view_K(np.array([[50.0, 0, 30], [0, 50.0, 20], [0, 0, 1]]), 60, 40)
    for rotvec in ([0.1, 0.5, 0.0], [1.3, 0.2, 0.0], [0.0, 3.0, 0.1]):  # includes a view near the pole
        R = so3.exp(np.array(rotvec))
        bbox = rtpt.footprint_bbox(R, rtpt.view_border_rays(kv, 120, 80), 128, 64)
        out = gae.render_sphere(hist, R, kv, 120, 80, bbox)
        ref = gae.render_sphere_numpy(hist, R, kv, 120, 80)
        assert ref.sum() > 0
        np.testing.assert_allclose(out, ref, atol=1e-4)
