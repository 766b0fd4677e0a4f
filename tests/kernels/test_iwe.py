"""Front-end IWE kernel: Taichi vs numpy twin, analytic gradient vs central differences (float64)."""
import numpy as np
import pytest

from ti_cmax import Camera
from ti_cmax.kernels import iwe, runtime

CAM = Camera(64, 48, 50.0, 52.0, 31.3, 24.1)


def _packet(n=3000, span=0.01, seed=0):
    """Random bearings over (and slightly beyond) the sensor, times in +-span/2."""
    rng = np.random.default_rng(seed)
    x = rng.uniform(-3, CAM.width + 2, n)
    y = rng.uniform(-3, CAM.height + 2, n)
    b = CAM.unproject(x, y)
    dts = rng.uniform(-span / 2, span / 2, n)
    return b, dts


OMEGAS = [(0.0, 0.0, 0.0), (0.8, -1.5, 0.4), (10.0, -3.0, 6.0)]


@pytest.mark.parametrize("measure", ["variance", "mean_square"])
@pytest.mark.parametrize("dtype, rtol", [(np.float64, 1e-9), (np.float32, 2e-3)])
@pytest.mark.parametrize("span", [0.01, 0.1])
def test_kernel_matches_numpy_twin(ti_runtime, measure, dtype, rtol, span):
    """Both paths of the kernels: every angle omega dt_k below 0.1 (the Rodrigues series alone, vectorised loops),
    and larger angles (span 0.1 s at 11.9 rad/s: up to 0.6 rad)."""
    b, dts = _packet(seed=1, span=span)
    ws = iwe.IWEWorkspace(CAM.width, CAM.height, dtype, capacity=len(dts))
    ws.set_packet(b, dts)
    for om in OMEGAS:
        c, g, n_in = ws.evaluate(om, CAM.K, measure)
        c_ref, g_ref = iwe.contrast_numpy(b, dts, om, CAM.K, CAM.width, CAM.height, measure)
        assert c == pytest.approx(c_ref, rel=rtol)
        np.testing.assert_allclose(g, g_ref, rtol=rtol, atol=rtol * np.abs(g_ref).max())
        assert 0 < n_in <= len(dts)
        # the cost alone, from the images (a dot product instead of the pass over the events; the image is cleared
        # between calls): the same value up to the summation's rounding
        c2, g2, n2 = ws.evaluate(om, CAM.K, measure, with_grad=False)
        assert c2 == pytest.approx(c_ref, rel=rtol) and not np.any(g2) and n2 == n_in
        assert c2 == pytest.approx(c, rel=1e-5 if dtype == np.float32 else 1e-12)


@pytest.mark.parametrize("measure", ["variance", "mean_square"])
@pytest.mark.parametrize("omega", OMEGAS)
@pytest.mark.parametrize("span", [0.01, 0.1])
def test_gradient_matches_central_differences(ti_runtime, measure, omega, span):
    b, dts = _packet(n=2000, seed=2, span=span)
    ws = iwe.IWEWorkspace(CAM.width, CAM.height, np.float64, capacity=len(dts))
    ws.set_packet(b, dts)
    c, g, _ = ws.evaluate(omega, CAM.K, measure)
    h = 1e-6
    fd = np.zeros(3)
    for i in range(3):
        e = np.zeros(3)
        e[i] = h
        fd[i] = (ws.evaluate(np.add(omega, e), CAM.K, measure)[0]
                 - ws.evaluate(np.subtract(omega, e), CAM.K, measure)[0]) / (2 * h)
    np.testing.assert_allclose(g, fd, rtol=1e-5, atol=1e-7 * np.abs(fd).max())
    # the numpy twin's gradient too (it is the oracle of the f32 kernel)
    g_np = iwe.contrast_numpy(b, dts, omega, CAM.K, CAM.width, CAM.height, measure)[1]
    np.testing.assert_allclose(g_np, fd, rtol=1e-5, atol=1e-7 * np.abs(fd).max())


def test_cost_is_the_contrast_of_the_blurred_image():
    """<I, G2 I> with zero padding equals ||G * I||^2 over the whole plane (J keeps the spilled mass), up to the
    dropped outer taps of G2 (below 1e-5 of its centre)."""
    b, dts = _packet(n=1500, seed=3)
    om = (1.0, 2.0, -0.5)
    img = iwe.vote_numpy(b, dts, om, CAM.K, CAM.width, CAM.height)
    r = 8
    canvas = np.pad(img, r)
    j_full = iwe._blur_np(canvas, iwe.gaussian_taps(1.0))
    npix = CAM.width * CAM.height
    ms = iwe.contrast_numpy(b, dts, om, CAM.K, CAM.width, CAM.height, "mean_square")[0]
    var = iwe.contrast_numpy(b, dts, om, CAM.K, CAM.width, CAM.height, "variance")[0]
    assert ms == pytest.approx(np.sum(j_full**2) / npix, rel=2e-5)
    assert len(iwe.gram_taps(1.0)) == 13  # radius 6 instead of 8
    assert var == pytest.approx(ms - (img.sum() / npix) ** 2, rel=1e-12)


def test_exact_rotation_and_rendering(ti_runtime):
    """The warp is the exact rotation exp([w]x dt) b; the rendered IWE equals the twin's votes."""
    from ti_cmax import so3

    b, dts = _packet(n=500, seed=4)
    om = np.array([10.0, -3.0, 6.0])
    xr = iwe.warp_numpy(b, dts, om)[0]
    ref = np.einsum("kij,kj->ki", so3.exp(om[None] * dts[:, None]), b)
    np.testing.assert_allclose(xr, ref, atol=1e-12)
    ws = iwe.IWEWorkspace(CAM.width, CAM.height, np.float64, capacity=8)
    ws.set_packet(b, dts)  # larger than the capacity: grows
    assert ws.capacity >= len(dts)
    np.testing.assert_allclose(ws.iwe(om, CAM.K, blurred=False),
                               iwe.vote_numpy(b, dts, om, CAM.K, CAM.width, CAM.height), atol=1e-9)


def test_unknown_measure_is_rejected():
    with pytest.raises(ValueError, match="unknown contrast measure"):
        iwe.measure_id("entropy")


@pytest.mark.parametrize("parts_per_thread", [0, 1, 2])
def test_vote_parts_and_ragged_width_match_twin(ti_runtime, parts_per_thread):
    """Votes split over several image copies (1 part, one per thread, two per thread), and a width that is not a
    multiple of the blur's SIMD group."""
    parts = max(1, parts_per_thread * runtime.num_threads())
    cam = Camera(61, 37, 40.0, 41.0, 30.2, 18.4)
    rng = np.random.default_rng(5)
    n = 1500
    b = cam.unproject(rng.uniform(-2, 62, n), rng.uniform(-2, 38, n))
    dts = rng.uniform(-0.005, 0.005, n)
    ws = iwe.IWEWorkspace(cam.width, cam.height, np.float64, capacity=n, parts=parts)
    ws.set_packet(b, dts)
    for om in OMEGAS:
        c, g, _ = ws.evaluate(om, cam.K)
        c_ref, g_ref = iwe.contrast_numpy(b, dts, om, cam.K, cam.width, cam.height)
        assert c == pytest.approx(c_ref, rel=1e-9)
        np.testing.assert_allclose(g, g_ref, rtol=1e-9, atol=1e-9 * np.abs(g_ref).max())


def test_parallel_evaluation_is_deterministic(ti_runtime):
    """Parts vote into their own copies on different threads (one 512-iteration task each) and partial sums are
    added in a fixed order: repeated evaluations give the same bits, and the result matches the twin. A task
    split across threads (another Taichi scheduling rule) would race on a copy and lose votes."""
    cam = Camera(240, 180, 199.0, 199.0, 120.0, 90.0)
    rng = np.random.default_rng(11)
    n = 20000
    b = cam.unproject(rng.uniform(0, 240, n), rng.uniform(0, 180, n))
    dts = rng.uniform(-0.02, 0.02, n)
    om = (0.3, -0.5, 0.8)
    c_ref, g_ref = iwe.contrast_numpy(b, dts, om, cam.K, cam.width, cam.height)
    for dtype in (np.float32, np.float64):
        ws = iwe.IWEWorkspace(cam.width, cam.height, dtype, capacity=n, parts=2)
        ws.set_packet(b, dts)
        results = {(c, *g) for c, g, _ in (ws.evaluate(om, cam.K) for _ in range(30))}
        assert len(results) == 1
        c, *g = results.pop()
        tol = 1e-9 if dtype == np.float64 else 1e-5  # f32: the gradient's sum cancels to ~1e-3 relative
        assert c == pytest.approx(c_ref, rel=tol)
        np.testing.assert_allclose(g, g_ref, rtol=tol if dtype == np.float64 else 3e-3, atol=tol * np.abs(g_ref).max())


def test_parts_that_would_share_a_task_are_rejected(ti_runtime):
    """With more parts than threads (and not a multiple), one CPU task would hold pieces of two copies."""
    threads = runtime.num_threads()
    if threads == 1:
        pytest.skip("every part count is safe with one thread")
    ws = iwe.IWEWorkspace(16, 8, np.float32, capacity=64, parts=threads + 1)
    with pytest.raises(ValueError, match="thread count"):
        ws.set_packet(np.array([[0.0, 0.0, 1.0]]), np.zeros(1))


def test_a_new_packet_rebinds_the_launches(ti_runtime):
    """The workspace's kernels are bound to the packet (runtime.BoundLaunch): each new packet, also one that grows
    the capacity (rebuilt kernels), is evaluated exactly as by a fresh workspace."""
    ws = iwe.IWEWorkspace(CAM.width, CAM.height, np.float64, capacity=1024)
    for n, seed in ((800, 2), (3000, 3), (500, 4)):  # 3000 > 1024: rebuilt with a doubled capacity
        b, dts = _packet(n=n, seed=seed)
        ws.set_packet(b, dts)
        fresh = iwe.IWEWorkspace(CAM.width, CAM.height, np.float64, capacity=4096)
        fresh.set_packet(b, dts)
        for om in OMEGAS:
            c, g, k = ws.evaluate(om, CAM.K)
            c2, g2, k2 = fresh.evaluate(om, CAM.K)
            assert c == c2 and np.array_equal(g, g2) and k == k2


def test_bound_launch_equals_the_kernel_call(ti_runtime):
    """runtime.BoundLaunch launches the same compiled kernel on the bound arrays and scalars (in place), ~2 us
    instead of Taichi's ~60 us of Python per call; rebinding switches the arrays; what it cannot bind is refused."""
    ti = runtime.ti

    @ti.kernel
    def axpy(x: ti.types.ndarray(dtype=ti.f64, ndim=1), y: ti.types.ndarray(dtype=ti.f64, ndim=1), a: ti.f64,
             n: ti.i32):
        for i in range(n):
            y[i] += a * x[i]

    x = np.arange(10.0)
    y_call, y_bound = np.ones(10), np.ones(10)
    axpy(x, y_call, 0.5, 7)
    launch = runtime.BoundLaunch(axpy, x, y_bound, 0.5, 7)
    launch()
    assert np.array_equal(y_call, y_bound)
    launch()  # again, in place
    axpy(x, y_call, 0.5, 7)
    assert np.array_equal(y_call, y_bound)
    other = np.zeros(10)
    launch.bind(x, other, 2.0, 10)
    launch()
    assert np.array_equal(other, 2.0 * x) and np.array_equal(y_call, y_bound)
    third = np.zeros(10)
    launch.set_array(1, third)  # one array only, the rest stays bound
    launch()
    assert np.array_equal(third, 2.0 * x) and np.array_equal(other, 2.0 * x)
    with pytest.raises(TypeError):
        launch.set_array(1, np.zeros(10, np.float32))  # another dtype: another compiled kernel
    with pytest.raises(TypeError):
        runtime.BoundLaunch(axpy, x, y_bound, 0.5)
    with pytest.raises(TypeError):
        runtime.BoundLaunch(axpy, x, np.ones(20)[::2], 0.5, 7)  # not contiguous


@pytest.mark.parametrize("parts", [None, 2])
@pytest.mark.parametrize("dtype, rtol", [(np.float64, 1e-9), (np.float32, 1e-3)])
def test_gradient_covariance_matches_numpy_twin(ti_runtime, dtype, rtol, parts):
    """The gradient's noise covariance from its per-event terms (gather's partial sums per group of 8 events): the
    twin computes the same from the numpy per-event terms, which sum to the gradient; also with parallel vote parts."""
    b, dts = _packet(n=3001, seed=7)
    ws = iwe.IWEWorkspace(CAM.width, CAM.height, dtype, capacity=len(dts), parts=parts)
    ws.set_packet(b, dts)
    for om in OMEGAS[:2]:
        _, g, _ = ws.evaluate(om, CAM.K)
        _, terms = iwe.contrast_numpy(b, dts, om, CAM.K, CAM.width, CAM.height, per_event=True)
        np.testing.assert_allclose(terms.sum(axis=0), iwe.contrast_numpy(b, dts, om, CAM.K, CAM.width, CAM.height)[1])
        ref = iwe.gradient_covariance_numpy(terms)
        cov = ws.gradient_covariance()
        assert np.all(np.linalg.eigvalsh(ref) > 0)
        np.testing.assert_allclose(cov, ref, rtol=rtol, atol=rtol * np.abs(ref).max())
    ws.set_packet(b[:120], dts[:120])  # 15 groups of 8 events: too few for an estimate
    ws.evaluate(OMEGAS[1], CAM.K)
    assert np.all(np.isnan(ws.gradient_covariance()))


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
@pytest.mark.parametrize("start, step, dithered", [(0, 1, False), (1, 3, True), (2, 5, True)])
def test_pack_matches_numpy_twin(ti_runtime, dtype, start, step, dithered):
    """Kernel ``pack`` reads the events' arrays in place, 1 of ``step`` from ``start``: bearing from the per-pixel
    table plus the dither rows, dt = t - t_ref in the workspace's float; it returns max |dt| of the rows."""
    rng = np.random.default_rng(7)
    total = 4000
    t = np.sort(rng.uniform(10.0, 10.02, total))
    x = rng.integers(0, CAM.width, total).astype(np.uint16)
    y = rng.integers(0, CAM.height, total).astype(np.uint16)
    lut = CAM.bearing_lut4.astype(dtype)
    dxy = rng.uniform(-0.01, 0.01, (total + 100, 2)).astype(dtype) if dithered else None
    n = len(range(start, total, step))
    ws = iwe.IWEWorkspace(CAM.width, CAM.height, dtype, capacity=64)  # the packet buffer grows beyond it
    t_ref = 10.01
    span = ws.pack(t, x, y, lut, CAM.width, start, step, n, t_ref, dxy, offset=17)
    want = iwe.pack_numpy(t, x, y, lut, start, step, n, t_ref, dxy, offset=17, width=CAM.width, dtype=dtype)
    assert ws.n == n
    np.testing.assert_array_equal(ws.rows(), want)
    assert span == pytest.approx(float(np.abs(want[:, 3]).max()), rel=1e-7)
    # the packed rows are what the evaluation reads: the same contrast as an upload of the same rows
    ref = iwe.IWEWorkspace(CAM.width, CAM.height, dtype, capacity=n)
    ref.set_packet(want[:, :3], want[:, 3])
    om = (0.8, -1.5, 0.4)
    assert ws.evaluate(om, CAM.K)[0] == ref.evaluate(om, CAM.K)[0]


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_separable_pack_is_the_per_pixel_pack(ti_runtime, dtype):
    """An undistorted camera's bearings are separable ((x - cx) / fx, (y - cy) / fy, 1): kernel ``pack`` from the
    table of max(width, height) rows gives the rows of the per-pixel table, bit for bit, as its numpy twin does."""
    cam = Camera(width=346, height=260, fx=250.0, fy=251.0, cx=172.3, cy=129.6)
    rng = np.random.default_rng(3)
    total = 5000
    t = np.sort(rng.uniform(1.0, 1.03, total))
    x = rng.integers(0, cam.width, total).astype(np.uint16)
    y = rng.integers(0, cam.height, total).astype(np.uint16)
    i = np.arange(max(cam.width, cam.height))
    table = np.zeros((len(i), 4), dtype)
    table[:, :3] = cam.unproject(i, i).astype(np.float32)
    dxy = rng.uniform(-0.01, 0.01, (total, 2)).astype(dtype)
    n = len(range(1, total, 2))
    ws = iwe.IWEWorkspace(cam.width, cam.height, dtype, capacity=n)
    span = ws.pack(t, x, y, table, cam.width, 1, 2, n, 1.015, dxy, offset=3, separable=True)
    want = iwe.pack_numpy(t, x, y, cam.bearing_lut4.astype(dtype), 1, 2, n, 1.015, dxy, offset=3, width=cam.width,
                          dtype=dtype)
    np.testing.assert_array_equal(ws.rows(), want)
    np.testing.assert_array_equal(iwe.pack_numpy(t, x, y, table, 1, 2, n, 1.015, dxy, offset=3, dtype=dtype,
                                                 separable=True), want)
    assert span == pytest.approx(float(np.abs(want[:, 3]).max()), rel=1e-7)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
@pytest.mark.parametrize("grid", [2, 16])
def test_grid_pack_matches_numpy_twin(ti_runtime, dtype, grid):
    """A distorted camera's bearings from a grid every ``grid`` pixels, interpolated bilinearly by kernel ``pack``:
    its numpy twin's numbers, and between the nodes the camera's own bearings up to the interpolation error."""
    cam = Camera(width=200, height=150, fx=180.0, fy=181.0, cx=99.2, cy=74.6, dist=(-0.1, 0.05, 0.0, 0.0, 0.0))
    rng = np.random.default_rng(9)
    total = 3000
    t = np.sort(rng.uniform(2.0, 2.02, total))
    x = rng.integers(0, cam.width, total).astype(np.uint16)
    y = rng.integers(0, cam.height, total).astype(np.uint16)
    x[:2], y[:2] = cam.width - 1, cam.height - 1  # the last pixel's cell: its far nodes lie past the sensor
    cols, rows = iwe.grid_nodes(cam.width, cam.height, grid)
    ny, nx = np.mgrid[0:rows, 0:cols] * grid
    table = np.zeros((rows * cols, 4), dtype)
    table[:, :3] = cam.unproject(nx.ravel(), ny.ravel())
    n = len(range(0, total, 3))
    ws = iwe.IWEWorkspace(cam.width, cam.height, dtype, capacity=n)
    ws.pack(t, x, y, table, cam.width, 0, 3, n, 2.01, grid=grid)
    want = iwe.pack_numpy(t, x, y, table, 0, 3, n, 2.01, width=cam.width, dtype=dtype, grid=grid)
    np.testing.assert_allclose(ws.rows(), want, rtol=1e-6 if dtype == np.float32 else 1e-13, atol=1e-7)
    exact = cam.bearings(x[::3], y[::3], np.float64)
    err = np.abs(want[:, :2] - exact[:, :2]) * [cam.fx, cam.fy]
    assert err.max() < (0.1 if grid == 16 else 0.01)
    assert np.all(want[:, 2] == 1.0)
