"""Panoramic IWE kernels (kernels/pano.py) vs their numpy twins, gradient vs central differences, seam wrap."""
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from ti_cmax.camera import Camera
from ti_cmax.spline import SO3Spline

W, H = 128, 64


def window_case(degree, yaw0=0.0, yaw_rate=1.0, n_events=2050, seed=0, return_times=False):
    """Random events of a 120x90 camera over the spline's valid range; trajectory yawing from yaw0."""
    from ti_cmax.kernels import pano

    rng = np.random.default_rng(seed)
    dt = 0.05
    m = 6
    kt = dt * np.arange(m)
    rotvec = np.stack([0.2 * np.sin(7 * kt), yaw0 + yaw_rate * kt, 0.1 * kt], axis=1)
    rotvec += rng.normal(size=(m, 3)) * 0.02
    spline = SO3Spline(degree, 0.0, dt, Rotation.from_rotvec(rotvec).as_matrix())
    start, end = spline.valid_time_range()
    t = np.sort(rng.uniform(start, end, n_events))
    cam = Camera.ideal(120, 90, 70.0)
    bearings = cam.bearings(rng.uniform(0, 119, n_events), rng.uniform(0, 89, n_events), dtype=np.float64)
    s, u = spline.support(pano.batch_mid_times(t, 100))
    global_map = pano.vote_map_numpy(bearings[::2], spline.evaluate(t[::2]) @ so3_small(0.03), W, H)
    return (spline, bearings, s, u, global_map) + ((t,) if return_times else ())


def so3_small(angle):
    return Rotation.from_rotvec([0.0, angle, angle]).as_matrix()


def test_equirect_center_and_seam_votes(ti_runtime):
    from ti_cmax.kernels import pano

    eye = np.eye(3)[None]
    # looking along +z: the centre pixel gets the whole vote
    img = pano.vote_map(np.array([[0.0, 0.0, 1.0]]), eye, W, H, dtype=np.float64)
    assert img[H // 2, W // 2] == pytest.approx(1.0) and img.sum() == pytest.approx(1.0)
    # lon just below +pi: u = w - 0.3 votes 0.3 into column w-1 and 0.7 into column 0 (u wraps)
    lon = np.pi - 0.3 * 2 * np.pi / W
    r_back = Rotation.from_rotvec([0.0, np.pi, 0.0]).as_matrix()  # camera looking along -z
    direction = np.array([np.sin(lon), 0.0, np.cos(lon)])
    b = r_back.T @ direction
    b = (b / b[2])[None]
    for dtype, tol in ((np.float32, 1e-4), (np.float64, 1e-9)):
        img = pano.vote_map(b, r_back[None], W, H, dtype=dtype)
        row = img[H // 2]
        assert row[W - 1] == pytest.approx(0.3, abs=tol) and row[0] == pytest.approx(0.7, abs=tol)
        assert img.sum() == pytest.approx(1.0, abs=tol)
        np.testing.assert_allclose(img, pano.vote_map_numpy(b, r_back[None], W, H), atol=tol)


def test_vote_map_matches_numpy_twin(ti_runtime):
    from ti_cmax.kernels import pano

    spline, bearings, s, u, _, t = window_case(1, yaw0=2.9, return_times=True)
    r_batch = spline.evaluate_at(s, u)
    twin = pano.vote_map_numpy(bearings, r_batch, W, H, batch_size=100)
    out = pano.vote_map(bearings, r_batch, W, H, batch_size=100, dtype=np.float64)
    np.testing.assert_allclose(out, twin, atol=1e-9)
    acc = pano.vote_map(bearings, r_batch, W, H, batch_size=100, out=out.copy(), dtype=np.float64)
    np.testing.assert_allclose(acc, 2 * twin, atol=1e-9)
    rendered = pano.render_map(bearings, t, spline.evaluate, W, H, batch_size=100, dtype=np.float64)
    np.testing.assert_allclose(rendered, twin, atol=1e-9)
    f32 = pano.vote_map(bearings, r_batch, W, H, batch_size=100)
    assert f32.dtype == np.float32
    np.testing.assert_allclose(f32, twin, atol=2e-3)
    assert f32.sum() == pytest.approx(len(bearings), rel=1e-5)


def test_event_area_and_density():
    from ti_cmax.kernels import pano

    img = np.zeros((4, 4))
    assert pano.event_area(img) == 0.0 and pano.event_density(img) == 0.0
    img[0, 0], img[1, 1] = 1.0, 3.0
    area = (1 - np.exp(-1.0)) + (1 - np.exp(-3.0))
    assert pano.event_area(img) == pytest.approx(area)
    assert pano.event_density(img) == pytest.approx(4.0 / area)
    assert pano.event_area(img, lambda0=2.0) == pytest.approx((1 - np.exp(-0.5)) + (1 - np.exp(-1.5)))


@pytest.mark.slow
@pytest.mark.parametrize("degree", [1, 3])
@pytest.mark.parametrize(
    "yaw0, yaw_rate, expect",
    [(0.0, 1.0, "inside"), (2.9, 1.0, "crosses seam"), (0.0, 40.0, "full width")],
)
def test_kernel_matches_numpy_twin(ti_runtime, degree, yaw0, yaw_rate, expect):
    from ti_cmax.kernels import pano, runtime

    spline, bearings, s, u, gmap = window_case(degree, yaw0, yaw_rate)
    ref_var, ref_grad, ref_img = pano.pano_iwe_numpy(
        bearings, s, u, spline.control_R, degree, W, H, 1.0, pano.blur_map(gmap, 1.0), 0.6, 100
    )
    # parts: copies of the window buffer voted into by one parallel part each (1: serial voting); a count that
    # gives every CPU task whole parts (runtime.check_parts)
    threads = runtime.num_threads()
    for dtype, rtol, parts in ((np.float64, 1e-10, 1), (np.float64, 1e-10, 2 * threads), (np.float32, 1e-4, threads)):
        obj = pano.PanoIWE(bearings, s, u, degree, W, H, 1.0, gmap, 0.6, 100, dtype=dtype, parts=parts)
        var, grad = obj.cost_and_grad(spline.control_R)
        assert var == pytest.approx(ref_var, rel=rtol)
        np.testing.assert_allclose(grad, ref_grad, atol=rtol * np.abs(ref_grad).max())
        assert obj.cost(spline.control_R) == var  # no float atomics: bit-reproducible
    r0, c0, bh, bw, wrap = obj.last_window
    if expect == "inside":
        assert not wrap and c0 + bw <= W
    elif expect == "crosses seam":
        assert not wrap and c0 + bw > W
    else:
        assert wrap and bw == W
    # local map: B(I_L) of the window (without alpha G)
    local = pano.PanoIWE(bearings, s, u, degree, W, H, 1.0, None, 0.0, 100, dtype=np.float64)
    np.testing.assert_allclose(local.local_map(spline.control_R), ref_img - 0.6 * pano.blur_map(gmap, 1.0),
                               atol=1e-10)


@pytest.mark.parametrize("yaw0, yaw_rate", [(0.0, 1.0), (2.9, 1.0), (0.0, 40.0)])  # inside, seam, full width
def test_raw_votes_match_the_vote_map_twin(ti_runtime, yaw0, yaw_rate):
    """PanoIWE.votes (how the back-end settles a stride into I_G) gives the unblurred votes of vote_map_numpy on its
    window, which holds every vote."""
    from ti_cmax.kernels import pano

    spline, bearings, s, u, _ = window_case(3, yaw0, yaw_rate)
    twin = pano.vote_map_numpy(bearings, spline.evaluate_at(s, u), W, H, batch_size=100)
    for dtype, atol in ((np.float64, 1e-10), (np.float32, 2e-3)):
        r0, cols, votes = pano.PanoIWE(bearings, s, u, 3, W, H, dtype=dtype).votes(spline.control_R)
        assert votes.dtype == dtype
        placed = np.zeros((H, W))
        placed[r0 : r0 + len(votes)][:, cols] = votes
        np.testing.assert_allclose(placed, twin, atol=atol)
    assert pano.PanoIWE(bearings[:0], s[:0], u[:0], 3, W, H).votes(spline.control_R) is None


def test_votes_on_kept_work_arrays_are_the_same_votes(ti_runtime):
    """The settle's PanoIWE on a VoteWork (arrays kept from one stride to the next) gives bitwise the votes of a
    fresh one; a smaller stride reuses the arrays a larger one made (no new memory), a larger one grows them."""
    from ti_cmax.kernels import pano

    spline, bearings, s, u, _ = window_case(3, 2.9, 1.0)
    work = pano.VoteWork()
    for n in (len(bearings), len(bearings) // 2, len(bearings)):  # batches of 100: whole ones
        b, ss, uu = bearings[:n], s[:-(-n // 100)], u[:-(-n // 100)]
        fresh = pano.PanoIWE(b, ss, uu, 3, W, H, parts=1).votes(spline.control_R)
        addresses = {k: a.ctypes.data for k, a in work._arrays.items()}
        kept = pano.PanoIWE(b, ss, uu, 3, W, H, parts=1, work=work).votes(spline.control_R)
        assert kept[0] == fresh[0] and np.array_equal(kept[1], fresh[1]) and np.array_equal(kept[2], fresh[2])
        if n < len(bearings):
            assert addresses == {k: a.ctypes.data for k, a in work._arrays.items()}
    assert np.shares_memory(kept[2], work._arrays["votes"])
    grown = work.take("uv", (10 * len(bearings), 2), np.float32)
    assert grown.shape == (10 * len(bearings), 2) and len(work._arrays["uv"]) >= 20 * len(bearings)
    assert not work.take("votes", (3, 5), np.float32, zero=True).any()


@pytest.mark.parametrize("degree", [1, 3])
def test_gradient_matches_central_differences(ti_runtime, degree):
    from ti_cmax.kernels import pano

    spline, bearings, s, u, gmap = window_case(degree, yaw0=2.9, seed=1)
    obj = pano.PanoIWE(bearings, s, u, degree, W, H, 1.0, gmap, 0.5, 100, dtype=np.float64)
    _, grad = obj.cost_and_grad(spline.control_R)
    h = 1e-7  # small: the bilinear-voting cost has kinks where events cross pixel borders
    numeric = np.zeros_like(grad)
    for k in range(spline.num_control):
        for d in range(3):
            delta = np.zeros((1, 3))
            delta[0, d] = h
            plus = spline.copy().retract(delta, k).control_R
            minus = spline.copy().retract(-delta, k).control_R
            numeric[k, d] = (obj.cost(plus) - obj.cost(minus)) / (2 * h)
    assert np.abs(grad).max() > 0
    np.testing.assert_allclose(grad, numeric, atol=1e-5 * np.abs(grad).max())


def test_batch_mid_times_of_a_sample_read_only_its_rows():
    """batch_mid_times(t, bs, index) = batch_mid_times(t[index], bs): the mid-times of a sample's batches without
    gathering the sample's times (the back-end's even sample of a window)."""
    from ti_cmax.kernels import pano

    t = np.sort(np.random.default_rng(3).uniform(0, 1, 1234))
    index = ((np.arange(517) + 0.5) * (1234 / 517)).astype(np.int64)
    np.testing.assert_array_equal(pano.batch_mid_times(t, 100, index), pano.batch_mid_times(t[index], 100))
    assert pano.batch_mid_times(t, 100)[-1] == 0.5 * (t[1200] + t[-1])  # the last batch partial
    assert len(pano.batch_mid_times(t, 100, index[:0])) == 0


def test_no_events_gives_constant_variance(ti_runtime):
    from ti_cmax.kernels import pano

    gmap = np.zeros((H, W))
    gmap[10, 20] = 4.0
    obj = pano.PanoIWE(np.zeros((0, 3)), np.zeros(0, int), np.zeros(0), 1, W, H, 1.0, gmap, 1.0, 100)
    var, grad = obj.cost_and_grad(np.broadcast_to(np.eye(3), (3, 3, 3)))
    g = pano.blur_map(gmap, 1.0)
    assert var == pytest.approx(g.var(), rel=1e-9)
    assert not grad.any()



def test_vote_map_is_bit_reproducible(ti_runtime):
    """The global map of the back-end (and CMax-GAE's sphere) is voted with serial plain adds: two runs give the
    same bits (parallel float atomics did not: their summation order varies)."""
    from ti_cmax import so3
    from ti_cmax.kernels.pano import vote_map

    rng = np.random.default_rng(0)
    n = 200_000
    b = rng.normal(size=(n, 3)).astype(np.float32)
    b[:, 2] = np.abs(b[:, 2]) + 2
    rot = so3.exp(rng.normal(scale=0.3, size=(n // 100, 3))).astype(np.float32)
    first = vote_map(b, rot, 256, 128, batch_size=100)
    again = vote_map(b, rot, 256, 128, batch_size=100)
    np.testing.assert_array_equal(first, again)
    assert first.sum(dtype=np.float64) == pytest.approx(n, rel=1e-5)


@pytest.mark.parametrize("lambda0", [1.0, 0.5])
def test_alpha_from_the_density_of_the_first_local_map(ti_runtime, lambda0):
    """alpha_from_density: alpha = rho(I_L) / rho_g from the first evaluation's raw local map (Eq. 16-17), the same
    as voting the events at those poses separately; the cost then equals the one with that alpha given."""
    from ti_cmax.kernels import pano

    spline, bearings, s, u, gmap = window_case(3, 0.5, 1.0)
    rho_g = pano.event_density(gmap, lambda0)
    local = pano.vote_map_numpy(bearings, spline.evaluate_at(s, u), W, H, batch_size=100)
    expected = pano.event_density(local, lambda0) / rho_g
    obj = pano.PanoIWE(bearings, s, u, 3, W, H, 1.0, gmap, 0.0, 100, dtype=np.float64,
                       alpha_from_density=(rho_g, lambda0))
    var, grad = obj.cost_and_grad(spline.control_R)
    assert obj.alpha == pytest.approx(expected, rel=1e-9)
    given = pano.PanoIWE(bearings, s, u, 3, W, H, 1.0, gmap, expected, 100, dtype=np.float64)
    var_g, grad_g = given.cost_and_grad(spline.control_R)
    assert var == pytest.approx(var_g, rel=1e-9)
    np.testing.assert_allclose(grad, grad_g, atol=1e-9 * np.abs(grad_g).max())
    later = obj.alpha
    obj.cost(spline.control_R @ so3_small(0.01))  # later evaluations keep the first one's alpha
    assert obj.alpha == later


def test_f32_projection_matches_equirect_numpy(ti_runtime):
    """The f32 path's polynomial atan2 (kernels/pano.py) against numpy's arctan2 on random directions, every octant:
    within 2.5e-6 rad (0.003 map px on the widest map)."""
    from ti_cmax.kernels import pano
    from ti_cmax.kernels.runtime import ti

    project, _ = pano._proj_funcs(ti.f32)

    @ti.kernel
    def k(x: ti.types.ndarray(dtype=ti.types.vector(3, ti.f32), ndim=1), o: ti.types.ndarray(dtype=ti.f32, ndim=2)):
        for i in range(x.shape[0]):
            pu, pv = project(x[i], 0, 0, ti.f32(1.0), ti.f32(1.0))  # (lon, lat) in radians
            o[i, 0] = pu
            o[i, 1] = pv

    x = np.random.default_rng(5).normal(size=(200_000, 3)).astype(np.float32)
    out = np.zeros((len(x), 2), np.float32)
    k(x, out)
    u, v = pano.equirect_numpy(x.astype(np.float64), 2 * np.pi, np.pi)  # width 2 pi: u - pi = lon
    np.testing.assert_allclose(out[:, 0], u - np.pi, atol=2.5e-6, rtol=0)
    np.testing.assert_allclose(out[:, 1], v - np.pi / 2, atol=2.5e-6, rtol=0)


def _revote_oracle(fine: np.ndarray, d: int) -> np.ndarray:
    """Each fine pixel's mass voted bilinearly at (column / d, row / d) of the coarse map (numpy twin of revote)."""
    from ti_cmax.kernels import bilinear

    h, w = fine.shape
    rows, cols = np.nonzero(fine)
    out = np.zeros((h // d, w // d))
    return bilinear.vote_numpy(out, cols / d, rows / d, weights=fine[rows, cols].astype(np.float64), wrap_u=True)


@pytest.mark.parametrize("d", [2, 3])
@pytest.mark.parametrize("r0, c0, bw", [(5, 17, 40), (0, 230, 40), (60, 3, 240), (7, 0, 240)])
def test_revote_matches_bilinear_votes_of_the_pixels(r0, c0, bw, d):
    """revote: a region's votes (a cyclic run of columns, across the seam, or every column) re-voted onto the map d
    times coarser equal the bilinear votes of each fine pixel's mass at its centre / d; the mass stays where the map
    holds it, and a pixel's re-vote is centred on it (first moments) with the rms of a coarse bilinear vote."""
    from ti_cmax.kernels.pano import revote

    w, h = 240, 72
    rng = np.random.default_rng(d + r0)
    votes = rng.uniform(0, 1, (min(12, h - r0), bw)).astype(np.float32) * (rng.uniform(size=(min(12, h - r0), bw)) < .3)
    cols = (c0 + np.arange(bw)) % w if bw < w else np.arange(w)
    fine = np.zeros((h, w), np.float32)
    fine[r0:r0 + len(votes)][:, cols] = votes
    rows, ccols, coarse = revote(votes, r0, cols, d, w, h)
    got = np.zeros((h // d, w // d))
    got[rows][:, ccols] += coarse
    want = _revote_oracle(fine, d)
    np.testing.assert_allclose(got, want, atol=1e-5)
    assert got.sum() == pytest.approx(want.sum(), rel=1e-5)
    # one pixel (away from the edges): centred at (c / d, r / d), variance (c mod d)(d - c mod d) fine px^2 per axis
    # (on average over the pixels (d^2 - 1) / 6: with the fine vote's 1/6, a coarse bilinear vote's d^2 / 6)
    one = np.zeros((1, 1), np.float32) + 1
    rows, ccols, coarse = revote(one, 31, np.array([101]), d, w, h)
    ys, xs = np.mgrid[rows, 0:len(ccols)]
    us = ccols[xs] * d
    assert np.sum(coarse * us) == pytest.approx(101, abs=1e-5) and np.sum(coarse * ys * d) == pytest.approx(31)
    assert np.sum(coarse * (us - 101.0) ** 2) == pytest.approx((101 % d) * (d - 101 % d), abs=1e-5)
