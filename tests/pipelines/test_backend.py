"""Back-end state: the incrementally maintained global map."""
import numpy as np
import pytest


def test_global_map_incremental_updates_match_full_recompute(ti_runtime):
    """GlobalMap keeps B(I_G), its sums and the event density equal to a from-scratch computation,
    also for votes straddling the longitude seam."""
    from ti_cmax.kernels.pano import blur_map, event_area
    from ti_cmax.pipelines.backend import GlobalMap

    rng = np.random.default_rng(4)
    w, h = 128, 64
    gm = GlobalMap(w, h, sigma=1.0, lambda0=1.0)
    for yaw in (0.0, np.pi - 0.05, 2.0):  # the second batch of events straddles u = 0 / w
        b = np.column_stack([rng.uniform(-0.4, 0.4, 3000), rng.uniform(-0.3, 0.3, 3000), np.ones(3000)])
        c, s_ = np.cos(yaw), np.sin(yaw)
        rot = np.array([[[c, 0, s_], [0, 1, 0], [-s_, 0, c]]])
        gm.add(b.astype(np.float32), rot, 3000, t_now=0.0)
    full = blur_map(gm.raw, 1.0)
    np.testing.assert_allclose(gm.blurred, full, atol=1e-4)
    assert gm.g_sum == pytest.approx(full.sum(), rel=1e-5)
    assert gm.g_sq == pytest.approx(np.sum(full * full), rel=1e-5)
    assert gm.n_events == pytest.approx(gm.raw.sum(dtype=np.float64), rel=1e-6)
    assert gm.area == pytest.approx(event_area(gm.raw), rel=1e-5)
    assert gm._scratch.max() == 0  # the scratch map is left clean


def test_global_map_takes_a_local_map_of_votes(ti_runtime):
    """GlobalMap.add_votes (the settle path: PanoIWE.votes's window) keeps I_G, B(I_G), the sums and the event area
    as GlobalMap.add does with the same events, across the longitude seam."""
    from ti_cmax import so3
    from ti_cmax.kernels.pano import PanoIWE, batch_mid_times
    from ti_cmax.pipelines.backend import GlobalMap
    from ti_cmax.spline import SO3Spline

    rng = np.random.default_rng(5)
    w, h, n = 256, 128, 4000
    b = np.column_stack([rng.uniform(-0.4, 0.4, n), rng.uniform(-0.3, 0.3, n), np.ones(n)]).astype(np.float32)
    sigma = 2.0  # the window's margin must be this blur's radius (8 px), not the default sigma's
    ref, local = GlobalMap(w, h, sigma, 1.0), GlobalMap(w, h, sigma, 1.0)
    for yaw in (0.3, np.pi - 0.05):  # the second stride straddles u = 0 / w
        spline = SO3Spline(3, 0.0, 0.05, so3.exp(np.outer(yaw + 0.5 * np.arange(6) * 0.05, [0.1, 1.0, 0.0])))
        start, end = spline.valid_time_range()
        mids = batch_mid_times(np.linspace(start, end, n), 100)
        ref.add(b, spline.evaluate(mids), 100, t_now=0.0)
        r0, cols, votes = PanoIWE(b, *spline.support(mids), 3, w, h, sigma=sigma).votes(spline.control_R)
        local.add_votes(r0, cols, votes, t_now=0.0)
    np.testing.assert_allclose(local.raw, ref.raw, atol=2e-3)
    np.testing.assert_allclose(local.blurred, ref.blurred, atol=2e-3)
    for name in ("g_sum", "g_sq", "n_events", "area"):
        assert getattr(local, name) == pytest.approx(getattr(ref, name), rel=1e-4), name


def test_global_map_keeps_the_ba_map_coarser(ti_runtime):
    """With downsample d, GlobalMap keeps the output map I_G at full resolution and the BA's map (ba_raw, B(I_G), its
    sums, N_e and the event area) d times coarser: the settled regions re-voted onto it, across the seam, equal to
    re-voting the whole map at once (set_raw, the loop closer's rebuild) and to a from-scratch blur."""
    from ti_cmax import so3
    from ti_cmax.kernels.pano import PanoIWE, batch_mid_times, blur_map, event_area, revote
    from ti_cmax.pipelines.backend import GlobalMap
    from ti_cmax.spline import SO3Spline

    rng = np.random.default_rng(6)
    w, h, n, d = 256, 128, 4000, 2
    b = np.column_stack([rng.uniform(-0.4, 0.4, n), rng.uniform(-0.3, 0.3, n), np.ones(n)]).astype(np.float32)
    full, coarse = GlobalMap(w, h, 1.0, 1.0), GlobalMap(w, h, 1.0, 1.0, downsample=d)
    assert coarse.ba_size == (w // d, h // d) and coarse.blurred.shape == (h // d, w // d)
    for yaw in (0.3, np.pi - 0.05, 0.4):  # the second stride straddles u = 0 / w
        spline = SO3Spline(3, 0.0, 0.05, so3.exp(np.outer(yaw + 0.5 * np.arange(6) * 0.05, [0.1, 1.0, 0.0])))
        start, end = spline.valid_time_range()
        mids = batch_mid_times(np.linspace(start, end, n), 100)
        local = PanoIWE(b, *spline.support(mids), 3, w, h).votes(spline.control_R)
        full.add_votes(*local, t_now=0.0)
        coarse.add_votes(*local, t_now=0.0)
    np.testing.assert_array_equal(coarse.raw, full.raw)  # the output map at full resolution
    want = revote(full.raw, 0, np.arange(w), d, w, h)[2]
    np.testing.assert_allclose(coarse.ba_raw, want, atol=1e-5)
    np.testing.assert_allclose(coarse.blurred, blur_map(want, 1.0), atol=1e-4)
    at_once = GlobalMap(w, h, 1.0, 1.0, downsample=d)
    at_once.set_raw(full.raw.copy())
    np.testing.assert_allclose(at_once.blurred, coarse.blurred, atol=1e-4)
    for gm in (coarse, at_once):
        assert gm.n_events == pytest.approx(full.n_events, rel=1e-4)
        assert gm.area == pytest.approx(event_area(want), rel=1e-4)
        assert gm.g_sum == pytest.approx(coarse.blurred.sum(dtype=np.float64), rel=1e-4)
        assert gm.g_sq == pytest.approx(np.sum(coarse.blurred.astype(np.float64) ** 2), rel=1e-4)
    with pytest.raises(ValueError):
        GlobalMap(250, 125, 1.0, 1.0, downsample=2)


def test_window_initialization_reaches_beyond_the_window_end():
    """Source samples that coincide with the window end up to rounding (100 Hz poses, 0.1 s windows, a start
    time like 0.066265000000000004) must not count as the sample beyond it: the window's last control poses
    would be left unconstrained (it made every later window of an RTPT refinement fail)."""
    from ti_cmax.config import BackendConfig
    from ti_cmax.pipelines.backend import SlidingWindowBackend
    from ti_cmax import so3

    t_start = 0.06626499999999999
    src_t = 0.066265000000000004 + 0.01 * np.arange(60)
    src_R = so3.exp(np.outer(src_t, [0.3, -1.0, 0.5]))
    from ti_cmax import Camera
    from ti_cmax.pipelines.sensor_defaults import resolve_backend

    be = SlidingWindowBackend(resolve_backend(BackendConfig(), Camera(240, 180, 200.0, 200.0, 119.5, 89.5)),
                              t_start, src_R[0])
    be.push_source_poses(src_t, src_R)
    t_end = be.window_end
    assert np.any(np.abs(src_t - t_end) < 1e-12)  # the case: a sample at the window end, to rounding
    be._initialize_until(t_end)
    assert be._anchor[0] > t_end + 1e-3
    times, _ = be._source_segment(t_start, t_end)
    assert times[-1] > t_end + 1e-3


def test_a_stream_shorter_than_one_window_whose_events_outlast_the_source(ti_runtime):
    """The whole stream in the first window, the last source pose 5 ms before the last event (the front-end's last
    packet ends there): the spline must reach the last event (it stopped at the last pose's knot interval and the
    BA raised 'outside the spline's valid range'; seen on the first 0.15 s of a 2 M ev/s recording)."""
    from ti_cmax import Camera, so3
    from ti_cmax.config import BackendConfig
    from ti_cmax.pipelines.backend import SlidingWindowBackend
    from ti_cmax.pipelines.sensor_defaults import resolve_backend

    cam = Camera(240, 180, 200.0, 200.0, 119.5, 89.5)
    rng = np.random.default_rng(1)
    t = np.sort(rng.uniform(0.0271, 0.1772, 30000))
    src_t = np.arange(0.0321, 0.1722, 0.005)  # ends 5 ms before the events, past the last knot the poses reach
    src_r = so3.exp(np.outer(src_t, [0.0, 0.5, 0.0]))
    be = SlidingWindowBackend(resolve_backend(BackendConfig(), cam), 0.0271, src_r[0])
    be.push_events(t, cam.bearings(rng.integers(0, 240, len(t)), rng.integers(0, 180, len(t))),
                   complete_until=float(t[-1]))
    be.push_source_poses(src_t, src_r)
    assert not be.ready()
    be.finish()
    assert len(be.windows) == 1 and be.windows[0].optimized
    assert be.spline.valid_time_range()[1] >= t[-1]
    traj = be.trajectory(1000.0)
    late = traj.at(np.array([src_t[-1], t[-1]]))  # extrapolated at the source's last angular velocity
    np.testing.assert_allclose(so3.log(late[0].T @ late[1])[1] / (t[-1] - src_t[-1]), 0.5, atol=0.1)


@pytest.mark.parametrize("field,value", [("backend_cg_step_guess", "newton"), ("backend_cg_max_line_evals", 0)])
def test_backend_rejects_bad_line_search_settings(field, value):
    """The CG line-search settings are config fields (YAML / --set): a bad value is one clear error naming the
    field, not a late ValueError or a line search that never evaluates."""
    from ti_cmax.config import BackendConfig
    from ti_cmax.errors import InputError
    from ti_cmax.pipelines.backend import SlidingWindowBackend

    with pytest.raises(InputError, match=field):
        SlidingWindowBackend(BackendConfig(**{field: value}), 0.0)


def test_carried_inverse_hessian_follows_the_free_control_poses():
    """The next window frees control poses 2..6 where the last one freed 0..4: the shared poses 2..4 keep their
    blocks, the new poses 5, 6 start uncoupled with the mean diagonal; nothing shared (windows without a BA in
    between) takes the last inverse Hessian as the template pose by pose; a window behind the last one, or no BA
    yet, gives a cold start."""
    from ti_cmax.config import BackendConfig
    from ti_cmax.pipelines.backend import SlidingWindowBackend

    be = SlidingWindowBackend.__new__(SlidingWindowBackend)
    rng = np.random.default_rng(0)
    a = rng.normal(size=(15, 15))
    h_prev = a @ a.T + 15 * np.eye(15)
    be._inv_hessian = (10, h_prev)
    h = be._carried_inv_hessian(12, 5)
    np.testing.assert_array_equal(h[:9, :9], h_prev[6:, 6:])
    np.testing.assert_array_equal(h[9:, :9], 0.0)
    np.testing.assert_allclose(np.diag(h)[9:], np.mean(np.diag(h_prev)))
    np.testing.assert_array_equal(be._carried_inv_hessian(15, 5), h_prev)
    h = be._carried_inv_hessian(30, 7)  # more free poses than the template: the rest start uncoupled
    np.testing.assert_array_equal(h[:15, :15], h_prev)
    np.testing.assert_array_equal(h[15:, :15], 0.0)
    np.testing.assert_allclose(np.diag(h)[15:], np.mean(np.diag(h_prev)))
    assert be._carried_inv_hessian(9, 5) is None
    be._inv_hessian = None
    assert be._carried_inv_hessian(12, 5) is None
    assert BackendConfig().backend_optimizer == "bfgs"


def test_source_poses_before_the_anchor_are_dropped_and_poses_ahead_unchanged():
    """On a long stream the back-end keeps only the source poses from its anchor on (memory and the per-packet
    append stay bounded); pose_at beyond the anchor still reads the re-anchored source at every time."""
    from ti_cmax import Camera, so3
    from ti_cmax.config import BackendConfig
    from ti_cmax.pipelines.backend import SlidingWindowBackend
    from ti_cmax.pipelines.backend_policies import EMPTY_WINDOWS_PER_FIT
    from ti_cmax.pipelines.sensor_defaults import resolve_backend
    from ti_cmax.trajectory import Trajectory

    cfg = resolve_backend(BackendConfig(), Camera(240, 180, 200.0, 200.0, 119.5, 89.5))
    src_t = 0.01 * np.arange(400)
    src_R = so3.exp(np.outer(src_t, [0.3, -1.0, 0.5]) + 0.1 * np.sin(np.outer(src_t, [1.0, 2.0, 3.0])))
    be = SlidingWindowBackend(cfg, 0.0)
    for k in range(len(src_t)):  # one pose per packet, as from the front-end; no events (no BA)
        be.push_source_poses(src_t[k:k + 1], src_R[k:k + 1])
        be.push_events(np.zeros(0), np.zeros((0, 3), np.float32), complete_until=float(src_t[k]))
        while be.ready():
            be.step()
    window = cfg.backend_time_window_size + cfg.backend_sliding_window_stride
    # (windows without events are fitted 10 strides at a time: the source kept spans at most that much more)
    window += EMPTY_WINDOWS_PER_FIT * cfg.backend_sliding_window_stride
    assert len(be.windows) > 30 and len(be._src_t) <= window / 0.01 + 3
    t_a, r_src_a, r_spl_a = be._anchor
    ahead = np.linspace(t_a + 1e-3, src_t[-1], 7)
    expected = r_spl_a @ r_src_a.T @ Trajectory(src_t, src_R).at(ahead)
    np.testing.assert_array_equal(be.pose_at(ahead), expected)


def test_event_buffer_ranges_drops_and_views_stay_valid():
    """The back-end's event buffer: ranges and drops equal slicing the concatenated stream, a view taken before
    later pushes (and a regrowth) still shows the same events, and memory follows the live part, not the stream."""
    from ti_cmax.pipelines.backend import _Buffer

    rng = np.random.default_rng(0)
    t_all = np.cumsum(rng.random(20_000) * 1e-4)
    b_all = rng.random((20_000, 3)).astype(np.float32)
    buf, start, view, most = _Buffer(), 0, None, 0
    for i0 in range(0, len(t_all), 700):  # chunks of 700 events; drop the head every few chunks
        buf.push(t_all[i0:i0 + 700], b_all[i0:i0 + 700])
        end = min(i0 + 700, len(t_all))
        if view is None and i0 >= 2100:
            view = (buf.range(t_all[1000], t_all[1500]), t_all[1000:1500].copy())
        if i0 % 2800 == 2100:
            start = int(np.searchsorted(t_all[:end], t_all[i0] - 0.02, side="left"))
            buf.drop_before(t_all[i0] - 0.02)
        assert np.array_equal(buf.t, t_all[start:end]) and np.array_equal(buf.b, b_all[start:end].T)
        t0, t1 = t_all[(start + end) // 2], t_all[end - 1]
        rt, rb = buf.range(t0, t1, include_end=True)
        assert np.array_equal(rt, t_all[(start + end) // 2:end]) and np.array_equal(rb, b_all[(start + end) // 2:end].T)
        most = max(most, end - start)
        assert len(buf._tt) <= 2 * (most + 700) + 1024  # bounded by the live events, not the 20 000 pushed
    (vt, _), expected = view
    assert np.array_equal(vt, expected)


def test_event_buffer_sizes_its_arrays_from_the_event_rate_and_reuses_their_front():
    """A buffer told its horizon (the span of events it holds) sizes its arrays at the first growth past a
    millisecond of events for GROWTH_SPANS horizons at the rate seen, so a steady stream never grows them again, and
    moves its live part to the front once the settled head is as large: the rows ever written stay within two live
    parts plus a chunk, whatever the length of the stream."""
    from ti_cmax.pipelines.backend import _Buffer

    rate, horizon, chunk = 1e6, 0.03, 2000  # events/s, s, events per push
    buf = _Buffer(horizon)
    t_all = np.arange(600_000) / rate
    b_all = np.zeros((len(t_all), 3), np.float32)
    arrays, most, highest = set(), 0, 0
    for i0 in range(0, len(t_all), chunk):
        buf.push(t_all[i0:i0 + chunk], b_all[i0:i0 + chunk])
        arrays.add(buf._tt.ctypes.data)
        highest = max(highest, buf._end)
        if i0 % (5 * chunk) == 0:  # settle: keep the last horizon of events
            buf.drop_before(t_all[i0 + chunk - 1] - horizon)
        most = max(most, len(buf.t))
        assert np.array_equal(buf.t, t_all[int(np.searchsorted(t_all, buf.t[0])):i0 + chunk])
    assert len(arrays) <= 3  # 1024 rows, the doubling up to a millisecond, the rate's size
    assert len(buf._tt) >= _Buffer.GROWTH_SPANS * horizon * rate * 0.9
    assert highest <= 2 * most + chunk


def test_event_buffer_falls_back_to_doubling_when_its_rate_sized_arrays_cannot_be_mapped(monkeypatch):
    """A rate estimate that asks for more memory than the system maps (a burst in the first millisecond) does not
    fail the run: the buffer takes twice the room it needs instead."""
    from ti_cmax.pipelines import backend

    real_empty = np.empty

    def empty(shape, *args, **kwargs):
        if (shape if isinstance(shape, int) else shape[0]) > 10_000:
            raise MemoryError("cannot map")
        return real_empty(shape, *args, **kwargs)

    buf = backend._Buffer(horizon=1000.0)  # 8000 s of events at the rate seen: more than this system "maps"
    t_all = np.arange(4000) * 1e-6
    monkeypatch.setattr(backend.np, "empty", empty)
    for i0 in range(0, 4000, 1000):
        buf.push(t_all[i0:i0 + 1000], np.zeros((1000, 3), np.float32))
    assert np.array_equal(buf.t, t_all) and len(buf._tt) <= 2 * 4000


@pytest.mark.parametrize("hold_view", [False, True])
def test_event_buffer_moves_its_live_part_in_place_when_no_view_is_held(hold_view):
    """When the spare room runs out and the settled head left room enough, the buffer moves its live part to the
    front of the same arrays (no new memory to fault in) while no view of them is held, and to new arrays while one
    is (the view keeps showing its events); ``reserve`` / ``commit`` (a writer filling rows in place) append as
    ``push`` does."""
    from ti_cmax.pipelines.backend import _Buffer

    t_all = np.arange(3000) * 1e-4
    b_all = np.random.default_rng(1).random((3000, 3)).astype(np.float32)
    buf = _Buffer()
    buf.push(t_all[:1024], b_all[:1024])
    buf.push(t_all[1024:2024], b_all[1024:2024])
    address = buf._tt.ctypes.data  # (a reference to the array would count as a view)
    assert len(buf._tt) == 2048
    buf.drop_before(t_all[1900])
    view = buf.range(t_all[1900], t_all[2000]) if hold_view else None
    tt, bb, row = buf.reserve(100)
    tt[row:row + 100], bb[:, row:row + 100] = t_all[2024:2124], b_all[2024:2124].T
    buf.commit(100)
    assert (buf._tt.ctypes.data == address and len(buf._tt) == 2048) == (not hold_view)
    assert np.array_equal(buf.t, t_all[1900:2124]) and np.array_equal(buf.b, b_all[1900:2124].T)
    if hold_view:
        assert np.array_equal(view[0], t_all[1900:2000]) and np.array_equal(view[1], b_all[1900:2000].T)
    with pytest.raises(ValueError):
        buf.commit(len(buf._tt))


@pytest.mark.parametrize("flags", ["given", "none", "off"])
def test_windows_over_which_the_source_measured_no_motion_get_no_ba(ti_runtime, flags):
    """Noise events seen by a still camera: a BA would fit its poses to them. Windows over which the source measured
    no motion (the front-end's moving flags) keep their initialization exactly; windows reaching the samples where
    the source moves get their BA, over the control poses of the moving part only. A source without flags (a given
    trajectory, IMU; here constant poses until 0.6 s) or backend_skip_still_windows=false: every window gets its BA."""
    from ti_cmax import Camera, so3
    from ti_cmax.config import BackendConfig
    from ti_cmax.pipelines.backend import SlidingWindowBackend
    from ti_cmax.pipelines.sensor_defaults import resolve_backend

    cam = Camera(240, 180, 200.0, 200.0, 119.5, 89.5)
    cfg = resolve_backend(BackendConfig(backend_skip_still_windows=flags != "off"), cam)
    rng = np.random.default_rng(0)
    t = np.sort(rng.uniform(0.0, 1.0, 60000))
    bearings = cam.bearings(rng.integers(0, 240, len(t)), rng.integers(0, 180, len(t)))
    src_t = 0.005 + 0.01 * np.arange(100)
    moving = src_t > 0.6
    src_r = so3.exp(np.outer(np.maximum(src_t - 0.6, 0.0), [0.0, 0.2, 0.0]))  # turning from 0.6 s on
    be = SlidingWindowBackend(cfg, 0.0)
    for k in range(len(src_t)):
        be.push_events(t[(t >= src_t[k] - 0.01) & (t < src_t[k])], bearings[(t >= src_t[k] - 0.01) & (t < src_t[k])],
                       complete_until=float(src_t[k]))
        be.push_source_poses(src_t[k:k + 1], src_r[k:k + 1], moving[k:k + 1] if flags == "given" else None)
        while be.ready():
            be.step()
    early = [w for w in be.windows if w.t_end < 0.58]
    late = [w for w in be.windows if w.t_start > 0.62]
    assert len(early) >= 3 and late
    if flags != "given":
        assert all(w.optimized and not w.still for w in early)
    else:
        assert all(w.still and not w.optimized for w in early) and all(not w.still for w in late)
        # the window that reaches the first motion (0.595 s on) moves only the control poses that shape R(t) there
        # (cubic: within 2 knot intervals): the still part's stay too
        knots = be.spline.knot_times()
        still_part = knots < 0.49
        np.testing.assert_array_equal(be.spline.control_R[still_part], np.eye(3)[None].repeat(np.sum(still_part), 0))
        assert np.any(be.spline.control_R[knots > 0.6] != np.eye(3))


@pytest.mark.parametrize("why", ["too few events", "BA rejected"])
def test_windows_without_ba_do_not_oscillate_after_a_kink(why):
    """A BA leaves the poses its events barely reach (the window's end) with some slope; the windows after it that
    get no BA (too few events, still, skipped in real time) are only fitted to the source. Fitting each window's new
    poses with the earlier ones fixed made cubic poses overshoot in turn (refining a pan's ground truth: +-2 to 4.8
    deg over its slow last 0.5 s); refitting the poses that shape the trajectory past the anchor keeps the
    trajectory a constant offset from the source (what re-anchoring means). A window whose BA is rejected (a false
    maximum: it keeps its initialization) is one without a BA too: its runs grew the same way (refining a pan's
    ground truth with every BA rejected: 0.5 deg at 8 s, 40 deg at 13 s)."""
    from ti_cmax import Camera, so3
    from ti_cmax.config import BackendConfig
    from ti_cmax.pipelines.backend import SlidingWindowBackend
    from ti_cmax.pipelines.sensor_defaults import resolve_backend

    camera = Camera(240, 180, 200.0, 200.0, 119.5, 89.5)
    rejected = why == "BA rejected"
    cfg = resolve_backend(BackendConfig(backend_max_correction=1e-12 if rejected else 0.1), camera)
    src_t = 0.01 * np.arange(200)
    src_r = so3.exp(np.outer(src_t, [0.0, 0.2, 0.0]))
    be = SlidingWindowBackend(cfg, 0.0)
    kinked = False
    # 500 events/s, below backend_min_ev_rate: no BA; or 20 000 events/s on random pixels: BAs, all rejected
    per_step = 200 if rejected else 5
    rng = np.random.default_rng(0)
    for k in range(len(src_t)):
        be.push_source_poses(src_t[k:k + 1], src_r[k:k + 1])
        xy = (rng.integers(0, 240, per_step), rng.integers(0, 180, per_step)) if rejected else \
            (np.full(per_step, 100.0), np.full(per_step, 80.0))
        be.push_events(src_t[k] - 0.01 / per_step * np.arange(per_step, 0, -1), camera.bearings(*xy),
                       complete_until=float(src_t[k]))
        while be.ready():
            be.step()
            if not kinked and be.window_start >= 0.5:  # as a BA would leave them: the last two poses turned 0.57 deg
                def kink(spline):
                    spline.control_R[-2:] = so3.exp(np.array([0.0, 0.0, 0.01])) @ spline.control_R[-2:]

                be.correct_poses(kink)
                kinked = True
    assert kinked and be.window_start > 1.5 and not any(w.optimized for w in be.windows)
    assert not rejected or sum(w.rejected for w in be.windows) >= 10
    t = np.linspace(0.8, be.window_start, 200)
    offset = so3.log(np.swapaxes(so3.exp(np.outer(t, [0.0, 0.2, 0.0])), 1, 2) @ be.spline.evaluate(t))
    assert np.degrees(np.ptp(offset, axis=0)).max() < 0.1  # 0.63 deg with the plain fit


def test_windows_without_events_are_fitted_with_the_next_one_that_has_some():
    """A pause of the stream: its empty windows cost no fit each (one fit over the pause, with the next window that
    has events); the poses over the pause are those of the source, as before."""
    from ti_cmax import Camera, so3
    from ti_cmax.config import BackendConfig
    from ti_cmax.pipelines.backend import SlidingWindowBackend
    from ti_cmax.pipelines.sensor_defaults import resolve_backend

    cfg = resolve_backend(BackendConfig(), Camera(240, 180, 200.0, 200.0, 119.5, 89.5))
    src_t = 0.01 * np.arange(200)
    src_r = so3.exp(np.outer(src_t, [0.0, 0.2, 0.0]))
    bearings = Camera(240, 180, 200.0, 200.0, 119.5, 89.5).bearings(np.full(5, 100.0), np.full(5, 80.0))
    be = SlidingWindowBackend(cfg, 0.0)
    fits = []
    fit = be._initialize_until
    be._initialize_until = lambda t, **kw: (fits.append(t), fit(t, **kw))
    for k in range(len(src_t)):  # events until 0.5 s and from 1.5 s on, none in between
        be.push_source_poses(src_t[k:k + 1], src_r[k:k + 1])
        ev_t = src_t[k] - 0.002 * np.arange(5, 0, -1) if not 0.5 < src_t[k] < 1.5 else np.zeros(0)
        be.push_events(ev_t, bearings[:len(ev_t)], complete_until=float(src_t[k]))
        while be.ready():
            be.step()
    paused = [w for w in be.windows if w.num_events == 0]
    assert len(paused) >= 8 and sum(0.6 < t < 1.45 for t in fits) == 1  # one fit for the 9 windows of 1 s
    t = np.linspace(0.1, be.window_start, 300)
    offset = so3.log(np.swapaxes(so3.exp(np.outer(t, [0.0, 0.2, 0.0])), 1, 2) @ be.spline.evaluate(t))
    assert np.degrees(np.abs(offset)).max() < 0.01


@pytest.mark.parametrize("gauge_free", [False, True])
def test_ba_objective_gradient_matches_central_differences(gauge_free):
    """The BA's objective over left perturbations of the free control poses (the first window's with their common
    rotation projected out) against central differences, in float64 on the full-map numpy twin of the cost."""
    from scipy.spatial.transform import Rotation

    from ti_cmax.camera import Camera
    from ti_cmax.kernels import pano
    from ti_cmax.pipelines.backend import perturbation_objective
    from ti_cmax.spline import SO3Spline

    rng = np.random.default_rng(3)
    kt = 0.05 * np.arange(7)
    spline = SO3Spline(3, 0.0, 0.05, Rotation.from_rotvec(np.stack([0.2 * np.sin(7 * kt), 1.0 * kt, 0.1 * kt], 1)
                                                         + rng.normal(size=(7, 3)) * 0.02).as_matrix())
    start, end = spline.valid_time_range()
    t = np.sort(rng.uniform(start, end, 1500))
    bearings = Camera.ideal(120, 90, 70.0).bearings(rng.uniform(0, 119, 1500), rng.uniform(0, 89, 1500),
                                                    dtype=np.float64)
    s, u = spline.support(pano.batch_mid_times(t, 100))
    gmap = pano.blur_map(pano.vote_map_numpy(bearings[::2], spline.evaluate(t[::2]), 128, 64), 1.0)

    def cost_and_grad(ctrl):
        var, grad, _ = pano.pano_iwe_numpy(bearings, s, u, ctrl, 3, 128, 64, 1.0, gmap, 0.5, 100)
        return var, grad

    first_free = 1
    step, objective = perturbation_objective(cost_and_grad, spline.control_R.copy(), first_free, gauge_free)
    x = rng.normal(size=3 * (7 - first_free)) * 0.01
    _, g = objective(x)
    eps = 1e-6
    fd = np.array([(objective(x + eps * e)[0] - objective(x - eps * e)[0]) / (2 * eps) for e in np.eye(len(x))])
    np.testing.assert_allclose(g, fd, rtol=1e-5, atol=1e-6 * np.abs(fd).max())
    if gauge_free:  # the common rotation is not a direction of the step
        np.testing.assert_allclose(step(x + 0.3).mean(axis=0), 0.0, atol=1e-12)
        np.testing.assert_allclose(g.reshape(-1, 3).sum(axis=0), 0.0, atol=1e-9 * np.abs(g).max())


def test_an_observer_is_notified_around_every_window_and_the_budget_skips_the_ba(ti_runtime):
    """The back-end notifies its observer (a no-op by default) before each window's BA, when a stride settles and
    after the window slides, in that order; a WindowBudget with ba_cap 0 gives no window a BA (the windows say
    why), and reading ``map`` never rebuilds it: only refresh_map asks the observer for a dropped map."""
    from ti_cmax import Camera, so3
    from ti_cmax.config import BackendConfig
    from ti_cmax.pipelines.backend import SlidingWindowBackend, WindowObserver
    from ti_cmax.pipelines.backend_policies import WindowBudget
    from ti_cmax.pipelines.sensor_defaults import resolve_backend

    camera = Camera(240, 180, 200.0, 200.0, 119.5, 89.5)
    cfg = resolve_backend(BackendConfig(), camera)
    rng = np.random.default_rng(1)

    class Recorder(WindowObserver):
        stage = "recorder"

        def __init__(self):
            self.calls = []

        def before_window(self, t0, t1, final=False, idle_only=False):
            self.calls.append(("before", t0))

        def settled(self, ev_t, ev_b, t0, moving):
            self.calls.append(("settled", t0))

        def after_window(self, t_now):
            self.calls.append(("after", t_now))

        def rebuilt_map(self):
            self.calls.append(("rebuilt", None))
            return kept

    be = SlidingWindowBackend(cfg, 0.0)
    assert type(be.observer) is WindowObserver  # the no-op default
    recorder = Recorder()
    be.attach(recorder)
    src_t = 0.01 * np.arange(60)
    be.push_source_poses(src_t, so3.exp(np.outer(src_t, [0.0, 0.5, 0.0])))
    n = 20_000
    t = np.sort(rng.uniform(0.0, src_t[-1], n))
    be.push_events(t, camera.bearings(rng.integers(0, 240, n), rng.integers(0, 180, n)))
    while be.ready():
        be.step(WindowBudget(ba_cap=0))
    assert len(be.windows) >= 3 and all(w.skipped and not w.optimized and not w.still for w in be.windows)
    stride = cfg.backend_sliding_window_stride
    for k in range(len(be.windows)):
        assert recorder.calls[3 * k:3 * k + 3] == [("before", pytest.approx(k * stride)),
                                                   ("settled", pytest.approx(k * stride)),
                                                   ("after", pytest.approx((k + 1) * stride))]
    assert "recorder" in be.clock.summary()["wall_seconds"]
    kept = be.map
    be.drop_map()
    assert be.map is None and ("rebuilt", None) not in recorder.calls
    assert be.refresh_map() is kept and recorder.calls[-1] == ("rebuilt", None)


def test_a_cold_start_climbs_on_a_subsample_first(ti_runtime):
    """A BFGS cold start on a large window climbs on every COARSE-th event first and then continues on all of them
    with the inverse Hessian it learnt: it ends at the plain cold start's optimum (within a tenth of a map pixel)
    with at most half the evaluations over all events."""
    from scipy.spatial.transform import Rotation

    from ti_cmax import so3
    from ti_cmax.config import BackendConfig
    from ti_cmax.kernels.pano import PanoIWE, batch_mid_times
    from ti_cmax.pipelines.backend import COARSE, COARSE_MIN_EVENTS, SlidingWindowBackend, perturbation_objective
    from ti_cmax.pipelines.backend_policies import FULL_BUDGET
    from ti_cmax.spline import SO3Spline

    rng = np.random.default_rng(4)
    kt = 0.05 * np.arange(7)
    truth = SO3Spline(3, 0.0, 0.05, Rotation.from_rotvec(np.stack([0.2 * np.sin(7 * kt), 1.0 * kt, 0.1 * kt], 1))
                      .as_matrix())
    n = COARSE_MIN_EVENTS + 20_000
    t = np.sort(rng.uniform(*truth.valid_time_range(), n))
    stars = rng.normal(size=(400, 3))
    stars[:, 2] = np.abs(stars[:, 2]) + 1.0  # ahead of the camera while it turns by about 0.3 rad
    world = stars[rng.integers(0, len(stars), n)] + rng.normal(scale=0.004, size=(n, 3))
    bearings = np.einsum("nji,nj->ni", truth.evaluate(t), world / np.linalg.norm(world, axis=1)[:, None])
    base = so3.exp(rng.normal(scale=0.004, size=(7, 3))) @ truth.control_R  # the initialisation, a little off
    width, height, first_free = 256, 128, 1
    s, u = truth.support(batch_mid_times(t, 100))

    def objective(rows):
        problem = PanoIWE(bearings[rows], *truth.support(batch_mid_times(t[rows], 100)), 3, width, height)
        return perturbation_objective(problem.cost_and_grad, base, first_free)[1]

    full_evaluations = []

    def maximise(coarse):
        be = SlidingWindowBackend.__new__(SlidingWindowBackend)
        be.cfg, be._inv_hessian, be._last_correction = BackendConfig(), None, None
        problem = PanoIWE(bearings, s, u, 3, width, height)
        step, perturbed = perturbation_objective(problem.cost_and_grad, base, first_free)

        def counted(x):
            full_evaluations.append(1)
            return perturbed(x)

        count = len(full_evaluations)
        result = be._maximise(problem, counted, base, first_free, 6, FULL_BUDGET, coarse=coarse)[0]
        return step(result.x), result, len(full_evaluations) - count

    plain, plain_result, plain_full = maximise(None)
    climbed, result, full = maximise(lambda alpha: objective(np.arange(0, n, COARSE)))
    assert plain_result.converged and result.converged
    assert full <= plain_full / 2, (full, plain_full)
    assert result.evaluations > full  # the coarse evaluations are counted
    pixel = 2 * np.pi / width
    assert np.abs(climbed - plain).max() < 0.1 * pixel
    assert np.abs(plain).max() > 0.3 * pixel  # a correction well beyond that agreement


def test_a_prepared_event_buffer_takes_a_stream_at_its_rate_in_its_own_memory():
    """Prepared for a rate, the buffer holds arrays sized as its first growth would size them, with the rows a steady
    stream writes (two horizons) written once already: a stream at that rate, settled as the back-end settles it,
    stays in those arrays and in those rows. Once events are held, ``prepare`` changes nothing."""
    from ti_cmax.pipelines.backend import _Buffer

    rate, horizon, chunk = 1e6, 0.03, 2000
    buf = _Buffer(horizon)
    buf.prepare(rate)
    address, capacity = buf._tt.ctypes.data, len(buf._tt)
    assert capacity == int(_Buffer.GROWTH_SPANS * horizon * rate) and buf._bb.shape == (3, capacity)
    assert not buf._tt[:int(2 * horizon * rate)].any() and len(buf.t) == 0
    t_all = np.arange(300_000) / rate
    b_all = np.ones((len(t_all), 3), np.float32)
    highest = 0
    for i0 in range(0, len(t_all), chunk):
        buf.push(t_all[i0:i0 + chunk], b_all[i0:i0 + chunk])
        highest = max(highest, buf._end)
        buf.drop_before(t_all[i0 + chunk - 1] - horizon)  # the live part: a horizon of events
    assert buf._tt.ctypes.data == address and highest <= 2 * (horizon * rate + chunk)
    buf.prepare(10 * rate)
    assert buf._tt.ctypes.data == address


def test_a_runner_prepared_for_a_rate_gives_its_back_end_that_buffer(ti_runtime):
    """``BackendRunner.prepare`` before the first events: the back-end created at them takes the prepared buffer."""
    from ti_cmax import Camera
    from ti_cmax.config import SlamConfig
    from ti_cmax.events import Events
    from ti_cmax.pipelines.online_backend import BackendRunner
    from ti_cmax.pipelines.sensor_defaults import resolve_config

    cam = Camera(64, 48, 50.0, 50.0, 31.5, 23.5)
    runner = BackendRunner(cam, resolve_config(SlamConfig(), cam))
    runner.prepare(2e5)
    prepared = runner._prepared._tt.ctypes.data
    rng = np.random.default_rng(0)
    n = 1000
    runner.push_events(Events(np.sort(rng.uniform(0, 0.005, n)), rng.integers(0, 64, n).astype(np.uint16),
                              rng.integers(0, 48, n).astype(np.uint16), np.ones(n, np.int8)))
    assert runner.backend.events._tt.ctypes.data == prepared and len(runner.backend.events.t) == n
