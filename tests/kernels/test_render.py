"""Simulator kernels vs their numpy twins (kernels/render.py)."""
import numpy as np
import pytest
from scipy.ndimage import gaussian_filter

from ti_cmax import so3
from ti_cmax.kernels import render as rk


@pytest.fixture(scope="module")
def pano():
    rng = np.random.default_rng(1)
    img = gaussian_filter(rng.uniform(0.05, 1.0, (48, 96)), 1.5, mode="wrap")
    return np.log(img).astype(np.float32)


def _unit_bearings(n, seed):
    b = np.random.default_rng(seed).normal(size=(n, 3))
    return b / np.linalg.norm(b, axis=1, keepdims=True)


def test_render_matches_numpy_everywhere_on_the_sphere(ti_runtime, pano):
    # directions all over the sphere: seam (lon = +-pi), poles, plus unnormalized bearings
    b = np.vstack([_unit_bearings(3000, 2), [[0, 0, -1], [1e-7, 0, -1], [-1e-7, 0, -1], [0, 1, 0], [0, -1, 1e-6]],
                   3.0 * _unit_bearings(50, 3)])
    for seed in range(3):
        r = so3.exp(np.random.default_rng(seed).normal(size=3))
        got = rk.render(pano, b, r)
        want = rk.render_numpy(pano, b, r)
        np.testing.assert_allclose(got, want, atol=2e-4)


def test_fast_atan2_projection_is_accurate(ti_runtime):
    """Ramp panoramas return the sampled (u, v) coordinates: checks the polynomial atan2 to ~1e-6 rad."""
    h, w = 2048, 4096
    u_ramp = np.broadcast_to(np.arange(w, dtype=np.float32), (h, w)).copy()
    v_ramp = np.broadcast_to(np.arange(h, dtype=np.float32)[:, None], (h, w)).copy()
    b = _unit_bearings(20000, 5)
    lon = np.arctan2(b[:, 0], b[:, 2])
    lat = np.arcsin(b[:, 1])
    b = b[(np.abs(lon) < 3.1) & (np.abs(lat) < 1.5)]  # away from the seam and the clamped pole rows
    u_want = w / 2 + w * np.arctan2(b[:, 0], b[:, 2]) / (2 * np.pi)
    v_want = h / 2 + h * np.arcsin(b[:, 1]) / np.pi
    np.testing.assert_allclose(rk.render(u_ramp, b, np.eye(3)), u_want, atol=w / (2 * np.pi) * 2e-6)
    np.testing.assert_allclose(rk.render(v_ramp, b, np.eye(3)), v_want, atol=h / np.pi * 2e-6)


def test_render_centre_of_panorama_is_straight_ahead(ti_runtime, pano):
    h, w = pano.shape
    got = rk.render(pano, np.array([[0.0, 0.0, 1.0]]), np.eye(3))
    assert got[0] == pytest.approx(pano[h // 2, w // 2], abs=1e-5)


def _chunk_inputs(pano, n_pix=120, k=40, seed=0):
    rng = np.random.default_rng(seed)
    bear = np.column_stack([rng.uniform(-0.6, 0.6, (n_pix, 2)), np.ones(n_pix)]).astype(np.float32)
    times = np.sort(rng.uniform(0.0, 0.05, k + 1))
    axis = np.array([0.3, 1.0, -0.2])
    rots = so3.exp(np.outer(times * 40.0, axis)).astype(np.float32)
    ref = rk.render(pano, bear, rots[0]) + rng.normal(0, 0.05, n_pix).astype(np.float32)
    cpos = rng.uniform(0.1, 0.3, n_pix).astype(np.float32)
    cneg = rng.uniform(0.1, 0.3, n_pix).astype(np.float32)
    last_t = np.full(n_pix, -np.inf)
    last_t[::3] = 0.01
    return bear, times, rots, ref, cpos, cneg, last_t


@pytest.mark.parametrize("refractory", [0.0, 2e-3])
def test_emission_matches_numpy(ti_runtime, pano, refractory):
    bear, times, rots, ref, cpos, cneg, last_t = _chunk_inputs(pano)
    width = 12
    lbuf, counts = rk.render_and_count(pano, bear, rots, times, ref, cpos, cneg, last_t, refractory)
    # the render buffer equals the single-render kernel at every time
    for k in (0, 17, len(times) - 1):
        np.testing.assert_array_equal(lbuf[:, k], rk.render(pano, bear, rots[k]))
    t_ref, x_ref, y_ref, p_ref, ref_new, lt_new = rk.emit_numpy(lbuf, times, ref, cpos, cneg, last_t, refractory,
                                                               width)
    ref_k, lt_k = ref.copy(), last_t.copy()
    t, x, y, p = rk.write_events(lbuf, times, ref_k, cpos, cneg, lt_k, refractory, counts, width)
    assert counts.sum() == len(t) == len(t_ref) > 100
    np.testing.assert_allclose(t, t_ref, rtol=0, atol=1e-9)
    np.testing.assert_array_equal(x, x_ref)
    np.testing.assert_array_equal(y, y_ref)
    np.testing.assert_array_equal(p, p_ref)
    np.testing.assert_array_equal(ref_k, ref_new)
    np.testing.assert_allclose(lt_k, lt_new, atol=1e-9)
    # timestamps lie inside the chunk; each pixel's events are in time order, spaced by the refractory period
    assert t.min() >= times[0] and t.max() <= times[-1]
    pix = y.astype(int) * width + x
    for i in np.unique(pix)[:40]:
        ti_ = t[pix == i]
        assert np.all(np.diff(ti_) >= refractory - 1e-12)


def test_chunks_continue_seamlessly(ti_runtime, pano):
    """Splitting the renders into two chunks (sharing the boundary render) gives the same events."""
    bear, times, rots, ref, cpos, cneg, last_t = _chunk_inputs(pano, seed=4)
    whole = rk.write_events(*_count(pano, bear, rots, times, ref.copy(), cpos, cneg, last_t.copy()), width=10)
    r2, l2 = ref.copy(), last_t.copy()
    parts = []
    for sl in (slice(0, 21), slice(20, None)):
        lbuf, counts = rk.render_and_count(pano, bear, rots[sl], times[sl], r2, cpos, cneg, l2, 0.0)
        parts.append(rk.write_events(lbuf, times[sl], r2, cpos, cneg, l2, 0.0, counts, 10))
    t = np.concatenate([q[0] for q in parts])
    pix = np.concatenate([q[2].astype(int) * 10 + q[1] for q in parts])
    o1 = np.lexsort((whole[0], whole[2].astype(int) * 10 + whole[1]))
    o2 = np.lexsort((t, pix))
    np.testing.assert_allclose(t[o2], whole[0][o1], atol=1e-12)


def _count(pano, bear, rots, times, ref, cpos, cneg, last_t):
    lbuf, counts = rk.render_and_count(pano, bear, rots, times, ref, cpos, cneg, last_t, 0.0)
    return lbuf, times, ref, cpos, cneg, last_t, 0.0, counts


def test_crossing_time_stays_within_the_render_interval():
    """A log intensity that crosses ref + c by one float32 ulp while ref + c rounds past it: the interpolated
    crossing fraction (r - L0) / (L1 - L0) came out as 4 (found by search; it put one event of an HD simulation
    9 us past its chunk's end, out of time order). Clamped, kernel and twin keep the event inside [t0, t1]."""
    from ti_cmax.kernels import render as rk

    f = np.float32
    ref, cp = f(-0.433524), f(0.45610973)
    l1 = f(0.022585714)
    l0 = np.nextafter(l1, f(-1))
    assert f(l1 - ref) >= cp and f(f(ref + cp) - l0) / f(l1 - l0) > 1.5  # the ill-conditioned case
    lbuf = np.array([[l0, l1]], np.float32)
    times = np.array([1.0, 1.00005])

    def state():  # write_events updates ref and last_t in place
        return np.array([ref]), np.array([cp]), np.array([cp]), np.full(1, -np.inf)

    t, *_ = rk.write_events(lbuf, times, *state(), 0.0, np.ones(1, np.int32), 1)
    tn, *_ = rk.emit_numpy(lbuf, times, *state(), 0.0, 1)
    assert len(t) == len(tn) == 1
    assert times[0] <= t[0] <= times[1] and times[0] <= tn[0] <= times[1]
