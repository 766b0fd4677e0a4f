"""Loop closure (pipelines/loop_closure.py): an injected drift over a revisit is found and removed, false revisits
(another region with similar texture, a textureless region) are rejected, loop_closure=false changes nothing."""
from dataclasses import replace

import numpy as np
import pytest

from ti_cmax import so3
from ti_cmax.config import BackendConfig, LoopClosureConfig
from ti_cmax.spline import SO3Spline

DURATION, TURNS, RATE = 5.0, 1.3, 120_000  # s, pan turns, events/s
DRIFT = np.radians(4.0)  # injected drift at the end (grows linearly from 0), about DRIFT_AXIS (world frame)
DRIFT_AXIS = np.array([0.3, 0.8, -0.5]) / np.linalg.norm([0.3, 0.8, -0.5])
LOOP = LoopClosureConfig(loop_closure=True, loop_registration_events=20000,  # as resolved for a DAVIS240C
                         loop_min_travel=240.0,  # as resolved for a 60 deg field of view
                         loop_check_drift_px=0.0)  # a check every loop_recent_time after a loop: more loops


def _pan(t, duration=DURATION, turns=TURNS):
    yaw = 2 * np.pi * turns * np.asarray(t) / duration
    return so3.exp(np.outer(yaw, [0.0, 1.0, 0.0]))


def _features(rng, n, yaw_range=(-np.pi, np.pi)):
    """n point features in clusters (blobs of 0.3-2 deg): texture at several scales, like a natural scene."""
    centers = n // 10
    lon = rng.uniform(*yaw_range, centers)
    lat = rng.uniform(-0.45, 0.45, centers)
    size = np.radians(rng.uniform(0.3, 2.0, centers))
    k = rng.integers(0, centers, n)
    lon, lat = lon[k] + rng.normal(0, 1, n) * size[k], lat[k] + rng.normal(0, 1, n) * size[k]
    return np.column_stack([np.cos(lat) * np.sin(lon), np.sin(lat), np.cos(lat) * np.cos(lon)])


def _events(seed=0, second_visit="same", duration=DURATION, turns=TURNS, rate=RATE):
    """Unit-depth bearings of a camera (60 x 45 deg field of view) panning over point features (one event = one
    feature seen at one time, 0.15 deg jitter). ``second_visit``: "same" scene; "other": after the first turn the
    camera sees a different random scene of the same density (similar texture); "textureless": the revisited
    sector [-90, 150] deg of longitude holds no features, only background-noise events, at both visits."""
    rng = np.random.default_rng(seed)
    feats = _features(rng, 20000)
    other = _features(rng, 20000)
    n = int(rate * duration * 3)
    t = np.sort(rng.uniform(0, duration, n))
    idx = rng.integers(0, len(feats), n)
    d = feats[idx].copy()
    if second_visit == "other":
        late = t > duration / turns * 0.9
        d[late] = other[idx[late]]
    if second_visit == "textureless":
        lon = np.arctan2(d[:, 0], d[:, 2])
        quiet = (lon > np.radians(-90)) & (lon < np.radians(150))
        m = int(quiet.sum())  # background noise: uniform directions, no structure
        lon_q, lat_q = rng.uniform(np.radians(-90), np.radians(150), m), rng.uniform(-0.45, 0.45, m)
        d[quiet] = np.column_stack([np.cos(lat_q) * np.sin(lon_q), np.sin(lat_q), np.cos(lat_q) * np.cos(lon_q)])
        keep = ~quiet | (rng.uniform(size=n) < 0.1)
        t, d = t[keep], d[keep]
    d = d + rng.normal(0, np.radians(0.15), d.shape)
    b = np.einsum("nji,nj->ni", _pan(t, duration, turns), d)  # R^T d
    vis = (b[:, 2] > 0.1) & (np.abs(b[:, 0] / b[:, 2]) < np.tan(np.radians(30))) & \
        (np.abs(b[:, 1] / b[:, 2]) < np.tan(np.radians(22.5)))
    t, b = t[vis], b[vis] / b[vis, 2:3]
    return t, b.astype(np.float32)


def _drifted(t):
    return so3.exp(np.outer(DRIFT * np.asarray(t) / DURATION, DRIFT_AXIS)) @ _pan(t)


def _spline(trajectory, dt=0.05, duration=DURATION):
    """Cubic spline fitted to the trajectory segment by segment, as the back-end grows it (a single lift of more
    than half a turn would wrap)."""
    spline = SO3Spline(3, -dt, dt, np.broadcast_to(trajectory([0.0])[0], (4, 3, 3)).copy())
    for t0 in np.arange(0, duration - 1e-9, 0.5):
        ts = np.linspace(t0, t0 + 0.5, 51)
        first_free = int(np.searchsorted(spline.knot_times(), t0 + 1e-9, side="right"))
        spline.fit_new_segment(ts, trajectory(ts), first_free=max(first_free, 1), refine_iters=1)
    return spline


def _run(t_ev, b_ev, trajectory, loop_cfg=LOOP, duration=DURATION, idle_slices=0, final=False):
    """Settle every stride of the events along the given trajectory (a spline fitted to it, no BA) with a loop
    closer attached, as the back-end does after each window (``idle_slices``: then that many slices of a sliced
    verification in flight, as the worker runs while idle; ``final``: the last window is the stream's last, as in
    SlidingWindowBackend.finish)."""
    from ti_cmax.pipelines.backend import SlidingWindowBackend
    from ti_cmax.pipelines.loop_closure import LoopCloser

    cfg = BackendConfig(pano_height=256, backend_min_ev_rate=10000.0, backend_max_window_events=-1)
    ts = np.arange(0, duration + 1e-9, 0.01)
    be = SlidingWindowBackend(cfg, 0.0)
    be.spline = _spline(trajectory, duration=duration)
    be.push_source_poses(ts, trajectory(ts))
    be._anchor_at(duration - 0.2)
    be.attach(LoopCloser(loop_cfg, be))
    be.push_events(t_ev, b_ev)
    stride = cfg.backend_sliding_window_stride
    n = int(round((duration - 0.2) / stride))
    for k in range(n):
        be.observer.before_window(k * stride, k * stride + cfg.backend_time_window_size, final and k == n - 1)
        be._settle(k * stride, (k + 1) * stride, moving=True)
        be.observer.after_window((k + 1) * stride)
        for _ in range(idle_slices):
            be.observer.idle_slice()
    return be


def _drifted_turns(duration=7.5, turns=2.3):
    """(events, drifted trajectory, duration) of a 2.3-turn pan with the injected drift: several loops to close."""
    pan = lambda t: _pan(t, duration, turns)  # noqa: E731
    drifted = lambda t: so3.exp(np.outer(DRIFT * np.asarray(t) / duration, DRIFT_AXIS)) @ pan(t)  # noqa: E731
    return _events(3, duration=duration, turns=turns, rate=60_000), drifted, duration


def _error(be, t, duration=DURATION, turns=TURNS):
    return np.degrees(so3.geodesic_angle(be.spline.evaluate(t), _pan(t, duration, turns)))


@pytest.mark.slow
def test_injected_drift_over_a_revisit_is_found_and_removed(ti_runtime):
    t_ev, b_ev = _events()
    be = _run(t_ev, b_ev, _drifted)
    applied = [e for e in be.observer.loops if e["applied"]]
    assert applied, be.observer.loops
    first = applied[0]
    # the drift between the old visit and the recent events is what the registration finds
    t_ref = first["t_ref"]  # when the recent events on the old map were seen
    expected = np.degrees(DRIFT) * (t_ref - first["t_old"]) / DURATION
    assert first["correction_deg"] == pytest.approx(expected, rel=0.1)
    assert first["confidence"] > first["confidence_before"]  # the registration improved the agreement
    # ... and removed: the error left at the recent events is within 10 % of the injected drift there (the old
    # visit's own drift stays: the old map is the reference)
    before = np.degrees(so3.geodesic_angle(_drifted([t_ref]), _pan([t_ref])))[0]
    t_old = first["t_old"]
    assert abs(_error(be, np.array([t_ref]))[0] - np.degrees(DRIFT) * t_old / DURATION) < 0.1 * before
    # the correction was spread between the visits: no jump, halfway the error is about halved too
    mid = 0.5 * (t_old + t_ref)
    assert _error(be, np.array([mid]))[0] < 0.6 * np.degrees(DRIFT) * mid / DURATION
    # the global map was rebuilt along the corrected trajectory: sharper than the drifted one
    ref = _run(t_ev, b_ev, _drifted, replace(LOOP, loop_min_confidence=2.0))
    assert not any(e["applied"] for e in ref.observer.loops)
    from ti_cmax.metrics import event_area_percent

    assert event_area_percent(be.refresh_map().raw) < event_area_percent(ref.refresh_map().raw)


@pytest.mark.slow
def test_every_revisit_is_closed_once(ti_runtime):
    """A 2.3-turn pan whose drift keeps growing: every later revisit closes the drift built up since the last
    loop (against the corrected map), and no correction is applied twice."""
    (t_ev, b_ev), drifted, duration = _drifted_turns()
    be = _run(t_ev, b_ev, drifted, duration=duration)
    applied = [e for e in be.observer.loops if e["applied"]]
    assert len(applied) >= 3, be.observer.loops  # the first return and the later checks of the revisits
    drift_deg = lambda t: np.degrees(DRIFT) * np.asarray(t) / duration  # noqa: E731
    first, later = applied[0], applied[1:]
    assert first["correction_deg"] > 0.5 * drift_deg(first["t_ref"] - first["t_old"])
    # a later loop corrects the drift since the previous one (about 1 s of it), not the total again
    for prev, e in zip(applied, later):
        assert e["correction_deg"] < 2.0 * drift_deg(e["t_ref"] - prev["t_ref"]) + 0.1, (prev, e)
    ts = np.linspace(first["t_ref"], applied[-1]["t_ref"], 30)
    err = np.degrees(so3.geodesic_angle(be.spline.evaluate(ts), _pan(ts, duration, 2.3)))
    assert err.max() < 0.25 * drift_deg(applied[-1]["t_ref"]), err  # 3.6 deg injected there


@pytest.mark.slow
@pytest.mark.parametrize("second_visit", ["other", "textureless"])
def test_false_revisits_are_rejected(ti_runtime, second_visit):
    t_ev, b_ev = _events(1, second_visit)
    be = _run(t_ev, b_ev, _pan)
    before = _spline(_pan)
    assert not any(e["accepted"] for e in be.observer.loops), be.observer.loops
    np.testing.assert_array_equal(be.spline.control_R, before.control_R)
    if second_visit == "other":  # the candidate was seen and judged, not missed
        assert be.observer.loops and all(e["confidence"] < LoopClosureConfig().loop_min_confidence
                                     for e in be.observer.loops)


def test_chain_pose_graph_spread_matches_least_squares():
    """so3.spread_correction is the minimizer of the linearized chain pose graph."""
    rng = np.random.default_rng(2)
    w = rng.uniform(0.1, 2.0, 7)
    phi = np.array([0.01, -0.02, 0.005])
    # unknowns x_1 .. x_6 (x_0 = 0, x_7 = phi): minimize sum (x_{k+1} - x_k)^2 / w_k, per axis
    n = len(w) - 1
    a = np.zeros((len(w), n))
    rhs = np.zeros((len(w), 3))
    for k in range(len(w)):
        if k < n:
            a[k, k] = 1.0
        if k > 0:
            a[k, k - 1] = -1.0
        if k == n:
            rhs[k] = -phi  # residual phi - x_n
    sw = 1 / np.sqrt(w)[:, None]
    x = np.linalg.lstsq(a * sw, rhs * sw, rcond=None)[0]
    got = so3.log(so3.spread_correction(w, phi))
    np.testing.assert_allclose(got[1:-1], x, atol=1e-12)
    np.testing.assert_allclose(got[0], 0, atol=1e-15)
    np.testing.assert_allclose(got[-1], phi, atol=1e-12)


@pytest.mark.slow
def test_loop_closure_false_is_todays_output_and_refine_cli_reports_loops(short_sequence, short_dataset, tmp_path):
    """Without a revisit the loop closer changes nothing (bitwise); loop_closure=false attaches none, and
    `refine --loop-closure` writes the "loops" list."""
    import json

    from ti_cmax.cli import main
    from ti_cmax.config import SlamConfig, load_config
    from ti_cmax.pipelines.slam import refine

    from ti_cmax.io import write_tum

    seq = short_sequence
    gt = seq.groundtruth.slice_time(0.0, 0.6)  # the first 0.6 s suffice (refine uses the events inside it)
    events = seq.events.slice_time(0.0, 0.6)
    runs = {on: refine(events, seq.camera, gt, load_config(SlamConfig, None, [f"loop_closure={on}", "pano_height=256"]))
            for on in ("false", "true")}
    off, on = runs["false"], runs["true"]
    assert "loops" not in off.report and on.report["loops"] == []
    assert SlamConfig().loop.loop_closure  # on by default
    np.testing.assert_array_equal(off.trajectory.R, on.trajectory.R)
    np.testing.assert_array_equal(off.map, on.map)
    out = tmp_path / "ref"
    write_tum(tmp_path / "gt.txt", gt)
    assert main(["refine", str(short_dataset), "--trajectory", str(tmp_path / "gt.txt"), "--out", str(out),
                 "--loop-closure", "--quiet", "--set", "pano_height=256"]) == 0
    report = json.loads((out / "report.json").read_text())
    assert report["loops"] == [] and report["parameters"]["loop"]["loop_closure"] is True


def test_old_map_holds_the_global_maps_weighted_votes(ti_runtime):
    """The loop closer's raw-only old map (no blur, sums or area) receives exactly the votes GlobalMap.add puts in
    I_G, weight included, across the longitude wrap."""
    from ti_cmax.pipelines.backend import GlobalMap
    from ti_cmax.pipelines.loop_closure import _RawMap

    t, b = _events(seed=3, duration=1.0)
    rot = _pan(t[::100] + 1.5)  # one rotation per batch of 100, the pan crossing longitude +-180 deg
    ref, old = GlobalMap(512, 256, 1.0, 1.0), _RawMap(512, 256)
    for weight in (1.0, 2.5):
        ref.add(b, rot, 100, 0.0, weight=weight)
        old.add(b, rot, 100, weight=weight)
    assert ref.raw.sum() > 0 and np.any(ref.raw[:, 0] > 0) and np.any(ref.raw[:, -1] > 0)
    np.testing.assert_array_equal(old.raw, ref.raw)
    assert not old._scratch.any()


def test_rebuilt_map_set_at_once_equals_the_settled_one(ti_runtime):
    """The rebuild after a loop sets I_G at once (GlobalMap.set_raw: one blur): the same blurred map, sums, event
    count and event area as settling the strides one by one; refused with pixel freezing."""
    from ti_cmax.pipelines.backend import GlobalMap

    t, b = _events(seed=4, duration=1.0)
    ref, at_once = GlobalMap(512, 256, 1.0, 1.0), GlobalMap(512, 256, 1.0, 1.0)
    for k, weight in enumerate((1.0, 2.5, 1.5)):
        ref.add(b, _pan(t[::100] + 1.2 * k), 100, 0.0, weight=weight)  # three strides, across the wrap
    at_once.set_raw(ref.raw.copy())
    np.testing.assert_allclose(at_once.blurred, ref.blurred, rtol=1e-5, atol=1e-6)
    for name in ("g_sum", "g_sq", "n_events", "area"):
        assert getattr(at_once, name) == pytest.approx(getattr(ref, name), rel=1e-6), name
    with pytest.raises(ValueError):
        GlobalMap(512, 256, 1.0, 1.0, max_update_time=1.0).set_raw(ref.raw.copy())


def test_verification_crops_are_exact():
    """The verification's shortcuts on large maps: the old map blurred on its rows alone equals the full-map blur
    (with its sums), its block sums on those rows equal the full map's, and the column box of the old regions is
    the shortest cyclic interval, across the wrap."""
    from ti_cmax.kernels.pano import blur_map
    from ti_cmax.pipelines.loop_closure import _blur_rows, _cyclic_span

    rng = np.random.default_rng(4)
    g = np.zeros((64, 128), np.float32)
    g[20:31] = rng.uniform(0, 3, (11, 128)).astype(np.float32)
    blurred, (total, squares) = _blur_rows(g, 20, 31, 1.0)
    full = blur_map(g, 1.0)
    np.testing.assert_allclose(blurred, full, atol=1e-5)
    np.testing.assert_allclose([total, squares], [full.sum(), np.sum(full ** 2)], rtol=1e-5)
    # the pyramid's block sums on the rows holding votes alone: the whole map's sums, bit for bit
    from ti_cmax.pipelines.loop_closure import _downsample

    rows = np.arange(20, 31)
    for f in (2, 4):
        np.testing.assert_array_equal(_downsample(g, rows, f), g.reshape(64 // f, f, 128 // f, f).sum(axis=(1, 3)))
    used = np.zeros(128, bool)
    used[[2, 3, 125]] = True
    assert _cyclic_span(used, 4).tolist() == [(c % 128) for c in range(121, 136)]
    assert len(_cyclic_span(used, 70)) == 128


def test_registration_events_follow_the_sensor_and_need_a_resolved_config():
    """loop_registration_events: 20 000 on a DAVIS240C (and smaller sensors), in proportion to the pixels above;
    a user value wins; the loop closer refuses the unresolved 0."""
    from ti_cmax.camera import Camera
    from ti_cmax.config import SlamConfig
    from ti_cmax.pipelines.backend import SlidingWindowBackend
    from ti_cmax.pipelines.loop_closure import LoopCloser
    from ti_cmax.pipelines.sensor_defaults import resolve_config

    def events_for(w, h, cfg=SlamConfig()):
        return resolve_config(cfg, Camera(w, h, 200.0, 200.0, w / 2, h / 2)).loop.loop_registration_events

    assert (events_for(128, 128), events_for(240, 180), events_for(640, 480), events_for(1280, 720)) == \
        (20000, 20000, 142000, 427000)
    assert events_for(640, 480, SlamConfig(loop=LOOP)) == 20000
    backend = SlidingWindowBackend(BackendConfig(pano_height=256, backend_min_ev_rate=1.0,
                                                 backend_max_window_events=-1), 0.0)
    with pytest.raises(ValueError, match="resolved"):
        LoopCloser(LoopClosureConfig(loop_closure=True), backend)


@pytest.mark.slow
def test_bench_level_holds_the_realtime_degradation(short_dataset):
    """bench_loops --level 4 (the drift benchmark's setting): the real-time controller's last level held offline,
    every window keeps the front-end's poses (BA skipped)."""
    from ti_cmax.config import SlamConfig
    from ti_cmax.pipelines.evaluation.bench_loops import run_at_level

    res = run_at_level(short_dataset, SlamConfig(), 4)
    backend = res.report["backend"]
    assert backend["windows"] > 5 and backend["windows_optimized"] == 0


@pytest.mark.slow
def test_checkpointed_rebuild_equals_the_full_one(ti_runtime):
    """After several applied loops (each later one rebuilt from the last rebuild's checkpoint), the old map, the
    age and visit maps and the global map equal a rebuild of every stored stride from scratch, bit for bit."""
    (t_ev, b_ev), drifted, duration = _drifted_turns()
    be = _run(t_ev, b_ev, drifted, duration=duration)
    lc = be.observer
    assert sum(bool(e["applied"]) for e in lc.loops) >= 3, lc.loops
    assert lc._checkpoint_start() > 0  # the last rebuild left a checkpoint the next one would use
    lc._rebuild()  # from the checkpoint
    got = (lc.old.raw.copy(), lc.age.copy(), lc.visit.copy(), be.refresh_map().raw.copy())
    assert lc._checkpoint[0] == lc._n_old
    lc._checkpoint = None
    lc._rebuild()  # every stride from scratch
    for a, b in zip(got, (lc.old.raw, lc.age, lc.visit, be.refresh_map().raw)):
        np.testing.assert_array_equal(a, b)
    # a correction that moves the checkpoint's poses invalidates it
    be.spline.control_R[2] = so3.exp(np.array([0.0, 1e-3, 0.0])) @ be.spline.control_R[2]
    assert lc._checkpoint_start() == 0


@pytest.mark.slow
def test_advanced_checkpoint_gives_the_same_run(ti_runtime, monkeypatch):
    """The checkpoint moved past each loop's recent block (_advance_checkpoint: later rebuilds vote fewer strides)
    gives the same loops, trajectory and maps, bit for bit, as rebuilding from the last rebuild's checkpoint."""
    from ti_cmax.pipelines.loop_closure import LoopCloser

    (t_ev, b_ev), drifted, duration = _drifted_turns()
    fast = _run(t_ev, b_ev, drifted, duration=duration)
    assert fast.observer.checkpoints_advanced >= 2 and sum(bool(e["applied"]) for e in fast.observer.loops) >= 3
    monkeypatch.setattr(LoopCloser, "_advance_checkpoint", lambda self: None)
    ref = _run(t_ev, b_ev, drifted, duration=duration)
    assert [e["correction_deg"] for e in fast.observer.loops] == [e["correction_deg"] for e in ref.observer.loops]
    np.testing.assert_array_equal(fast.spline.control_R, ref.spline.control_R)
    for a, b in ((fast.observer.old.raw, ref.observer.old.raw), (fast.observer.age, ref.observer.age),
                 (fast.observer.visit, ref.observer.visit), (fast.refresh_map().raw, ref.refresh_map().raw)):
        np.testing.assert_array_equal(a, b)


@pytest.mark.slow
def test_sliced_verification_registers_as_at_once_and_still_closes_the_loop(ti_runtime):
    """In real time (LoopCloser.slice_seconds) a verification runs in slices: one before each window here (budget
    0) and 5 in the idle time after it: the registration finds what the verification at once finds (the same poses and maps as detected,
    bit for bit), each slice a small part of the whole, the result applies windows later and still removes the
    drift; the map rebuild after it, in slices as well, equals the rebuild at once."""
    import time

    from ti_cmax.pipelines import loop_closure

    t_ev, b_ev = _events()
    # the age rule alone: the first candidate is then the loop to close (with loop_min_travel a check 0.2 s earlier,
    # at 20 % overlap, runs off and is rejected, and the next one is still in flight when this short run ends)
    cfg = replace(LOOP, loop_min_travel=-1.0)
    at_once = _run(t_ev, b_ev, _drifted, cfg)
    calls = []
    original = loop_closure._Slices.resume

    def resume(self):  # CPU seconds: wall time counts a preemption by other jobs as a long slice (a 73 ms "slice" once)
        tic = time.process_time()
        original(self)
        calls.append(time.process_time() - tic)

    loop_closure._Slices.resume = resume
    old_init = loop_closure.LoopCloser.__init__

    def init(self, *a, **k):  # sliced as in real time (built so: its optimizer is imported then, not in a slice)
        old_init(self, *a, **{**k, "slice_seconds": 0.0})

    loop_closure.LoopCloser.__init__ = init
    try:
        sliced = _run(t_ev, b_ev, _drifted, cfg, idle_slices=5)
    finally:
        loop_closure._Slices.resume, loop_closure.LoopCloser.__init__ = original, old_init
    first, ref = sliced.observer.loops[0], at_once.observer.loops[0]
    assert first["sliced"] and first["time"] == ref["time"]
    for key in ("correction_deg", "confidence", "confidence_before", "peak_ratio", "accepted"):
        assert first[key] == ref[key], key
    assert len(calls) > 20 and max(calls) < 0.5 * ref["seconds"]  # many slices, each a small part of the whole
    applied = [e for e in sliced.observer.loops if e["applied"]]
    assert applied
    lc = sliced.observer
    lc.drain()  # the end of the stream: a map rebuild still in flight (in slices too) at once
    assert lc._task is None and not lc.pending()
    # the rebuild in slices (the old map meanwhile in use, the strides aged meanwhile caught up) equals one at once
    got = (lc.old.raw.copy(), lc.age.copy(), lc.visit.copy(), sliced.refresh_map().raw.copy())
    lc._checkpoint, lc.slice_seconds = None, None
    lc._rebuild()
    for a, b in zip(got, (lc.old.raw, lc.age, lc.visit, sliced.refresh_map().raw)):
        np.testing.assert_array_equal(a, b)
    # the drift is removed as well: the error at the end of the run within 25 % of the at-once run's plus 0.1 deg
    t_end = np.array([DURATION - 0.5])
    assert _error(sliced, t_end)[0] < 1.25 * _error(at_once, t_end)[0] + 0.1 < np.degrees(DRIFT) * 0.5


@pytest.mark.slow
def test_backend_worker_runs_sliced_verifications(short_sequence):
    """With a back-end worker process and loop_slice_seconds (what `slam --realtime` sets), the verifications run
    in slices there (between windows and while idle) and reaches report.json's "loops" (short checks forced by
    loop_min_age=0.3 s on a 1.2 s sequence)."""
    from ti_cmax.config import SlamConfig, load_config
    from ti_cmax.pipelines.slam import OnlineSlam

    cfg = load_config(SlamConfig, None, ["loop_closure=true", "loop_min_age=0.3", "loop_recent_time=0.2"])
    online = OnlineSlam(short_sequence.camera, cfg, backend_process=True, loop_slice_seconds=0.0)
    ev = short_sequence.events
    for i in range(0, len(ev), 50_000):
        online.push(ev[i:i + 50_000])
    result = online.close()
    loops = result.report["loops"]
    # sliced until the end of the stream (then the last windows verify at once: LoopCloser.drain)
    assert loops and loops[0].get("sliced") and all(e.get("sliced") for e in loops[:-1]), loops
    assert all(e["reason"] for e in loops)
    summary = result.report["backend"]["loop_closure"]
    assert summary["candidates"] == len(loops) and summary["longest_call_cpu_seconds"] > 0


def test_texture_equals_the_scipy_twin():
    """The confidence test's texture (metrics.local_texture, OpenCV blur) equals its scipy twin."""
    from scipy import ndimage

    from ti_cmax.metrics import local_texture

    def twin(img, sigma, wrap):
        mode = ("constant", "wrap" if wrap else "constant")
        hp = img - ndimage.gaussian_filter(img, sigma, mode=mode)
        rms = np.sqrt(np.maximum(ndimage.gaussian_filter(hp * hp, sigma, mode=mode), 0.0))
        return hp / (rms + 1e-3 * float(rms.max()) + 1e-300)

    rng = np.random.default_rng(5)
    img = rng.uniform(0, 1, (40, 70)) * (rng.uniform(size=(40, 70)) < 0.3)
    for wrap in (False, True):
        np.testing.assert_allclose(local_texture(img, 3, wrap_columns=wrap), twin(img, 3, wrap), rtol=1e-9,
                                   atol=1e-9)


@pytest.mark.slow
def test_old_map_votes_wait_for_a_verification(ti_runtime):
    """Ageing marks the age and visit maps only: before any verification no old-map vote is cast (a run without a
    revisit never pays for them); voted later, the old map equals the one voted at ageing, bit for bit."""
    from ti_cmax.pipelines.loop_closure import _RawMap

    t_ev, b_ev = _events()
    lc = _run(t_ev, b_ev, _pan, duration=3.0).observer  # before loop_min_age + loop_recent_time: no check
    assert not lc.loops and lc._n_old > 10 and lc._n_voted == 0 and not lc.old.raw.any()
    lc._vote_aged(lc._n_old)
    eager = (_RawMap(lc.old.width, lc.old.height), np.full_like(lc.age, -np.inf), np.full_like(lc.visit, -np.inf))
    for chunk in lc.chunks[:lc._n_old]:
        lc._age_chunk(chunk, eager)
    for a, b in zip((lc.old.raw, lc.age, lc.visit), (eager[0].raw, eager[1], eager[2])):
        np.testing.assert_array_equal(a, b)


@pytest.mark.slow
def test_checks_after_a_loop_wait_for_the_drift_to_build_up(ti_runtime):
    """loop_check_drift_px: after an applied loop the next check waits until the drift rate that loop measured
    has moved the map by that many pixels (at most loop_min_age); 0 checks again after loop_recent_time."""
    (t_ev, b_ev), drifted, duration = _drifted_turns()
    runs = {px: _run(t_ev, b_ev, drifted, replace(LOOP, loop_check_drift_px=px), duration=duration).observer
            for px in (0.0, 1e4)}
    for px, lc in runs.items():
        applied = [i for i, e in enumerate(lc.loops) if e["applied"]]
        assert applied, lc.loops
        gap = LOOP.loop_recent_time if px == 0 else LOOP.loop_min_age
        for i in applied[:-1]:
            assert lc.loops[i + 1]["time"] - lc.loops[i]["time"] == pytest.approx(gap, abs=0.11), lc.loops
    assert len(runs[1e4].loops) < len(runs[0.0].loops)


@pytest.mark.slow
def test_global_map_is_rebuilt_once_when_read(ti_runtime, monkeypatch):
    """Without BA between them (the real-time controller's level 4) several applied loops cost one global-map
    rebuild, when the map is read; the strides settled meanwhile go to the store only (no map to vote into), and
    the map read equals a rebuild of the old map plus every stored stride along the corrected poses, bit for bit.
    (The verifications evaluate no cost of their own: BFGS's first evaluation gives the scale.)"""
    from ti_cmax.kernels.pano import PanoIWE

    costs = []
    monkeypatch.setattr(PanoIWE, "cost", lambda self, control_R: costs.append(1) or 0.0)
    (t_ev, b_ev), drifted, duration = _drifted_turns()
    be = _run(t_ev, b_ev, drifted, duration=duration)
    assert not costs
    lc = be.observer
    assert sum(bool(e["applied"]) for e in lc.loops) >= 3, lc.loops
    assert lc.map_stale and be.map is None and lc.map_rebuilds == 0
    lazy = be.refresh_map().raw.copy()
    assert lc.map_rebuilds == 1 and not lc.map_stale and be.refresh_map() is be.map
    lc._checkpoint = None
    lc._rebuild()  # every stride from scratch along the corrected spline: stale again
    assert lc.map_stale
    np.testing.assert_array_equal(be.refresh_map().raw, lazy)
    assert lc.map_rebuilds == 2


def test_fast_pan_revisits_count_by_the_rotation_travelled(ti_runtime):
    """2 turns in 4 s: the camera is back over a region 1.3-1.7 s after it left it, sooner than loop_min_age (3 s).
    The rotation travelled since (loop_min_travel) makes it a revisit: the drift is closed; by age alone the
    revisits are missed and the drift stays."""
    duration, turns = 4.0, 2.0
    pan = lambda t: _pan(t, duration, turns)  # noqa: E731
    drifted = lambda t: so3.exp(np.outer(DRIFT * np.asarray(t) / duration, DRIFT_AXIS)) @ pan(t)  # noqa: E731
    t_ev, b_ev = _events(3, duration=duration, turns=turns, rate=60_000)
    # the single-rotation closure alone (the joint refinement, tested on its own, also moves the poses before the
    # old visit: without a window BA in this test nothing tells it the truth)
    cfg = replace(LOOP, loop_joint_refinement=False)
    be = _run(t_ev, b_ev, drifted, cfg, duration=duration)
    age_only = _run(t_ev, b_ev, drifted, replace(cfg, loop_min_travel=-1.0), duration=duration)
    applied = [e for e in be.observer.loops if e["applied"]]
    assert applied and applied[0]["time"] < 3.0, be.observer.loops
    assert not any(e["applied"] for e in age_only.observer.loops), age_only.observer.loops
    # over the span the loops closed (the drift, 1 deg/s, builds up again after the last one)
    ts = np.linspace(applied[0]["t_ref"], applied[-1]["t_ref"], 10)
    err = np.degrees(so3.geodesic_angle(be.spline.evaluate(ts), pan(ts)))
    err_age = np.degrees(so3.geodesic_angle(age_only.spline.evaluate(ts), pan(ts)))
    assert err.max() < 0.25 * err_age.min(), (err, err_age)


@pytest.mark.slow
def test_the_last_window_closes_the_drift_since_the_last_check(ti_runtime):
    """At the end of the stream (the back-end's last window) a check runs when the last verification was at least
    loop_recent_time before: the drift built up since the last applied loop is closed there, not left to a check
    scheduled after the end. Before the last window the same run."""
    (t_ev, b_ev), drifted, duration = _drifted_turns()
    # after a loop the next check waits loop_min_age; the single-rotation closure alone (the joint refinement,
    # tested on its own, also moves the poses before the old visit)
    cfg = replace(LOOP, loop_check_drift_px=1e4, loop_joint_refinement=False)
    plain = _run(t_ev, b_ev, drifted, cfg, duration=duration).observer
    be = _run(t_ev, b_ev, drifted, cfg, duration=duration, final=True)
    lc = be.observer
    assert [e["time"] for e in lc.loops[:-1]] == [e["time"] for e in plain.loops], (lc.loops, plain.loops)
    last = lc.loops[-1]
    assert last["applied"] and last["time"] > plain.loops[-1]["time"] + cfg.loop_recent_time, lc.loops
    assert last["time"] > duration - 0.2 - 2 * BackendConfig().backend_time_window_size
    ts = np.linspace(last["t_ref"] - 0.2, last["t_ref"], 3)  # (before them the spread correction tapers)
    err, err_plain = _error(be, ts, duration, 2.3), _error(plain.backend, ts, duration, 2.3)
    assert err.max() < 0.5 * err_plain.min(), (err, err_plain)


def test_error_trace_gives_the_first_turns_part_of_the_abs_error():
    """bench_loops.error_trace: the part of the abs RMSE from the poses before the first full turn (what a loop
    closer anchored to the first turn's map cannot remove): all of it when only the first turn errs, none when
    only the second does."""
    import re

    from ti_cmax.pipelines.evaluation.bench_loops import error_trace
    from ti_cmax.trajectory import Trajectory

    t = np.arange(0, 4.0, 0.01)
    gt = Trajectory(t, _pan(t, 4.0, 2.0))  # 2 turns in 4 s: the first ends at 2 s
    for erring, share in (((t > 0.3) & (t < 1.8), 1.0), (t > 2.2, 0.0)):  # (none at the alignment time, 0.1 s)
        tilt = so3.exp(np.outer(np.where(erring, np.radians(0.5) * np.sin(3 * t), 0.0), [1.0, 0.0, 0.0]))
        head = error_trace(gt, Trajectory(t, tilt @ gt.R), 0.5).splitlines()[0]
        total, part = (float(x) for x in re.findall(r"abs RMSE ([\d.]+) deg.*first turn's part ([\d.]+) deg", head)[0])
        assert total > 0.1 and part == pytest.approx(share * total, abs=0.002), head


@pytest.mark.slow
def test_a_revisit_after_a_full_turn_refines_the_visits_jointly(ti_runtime):
    """Past a full turn of rotation a verified revisit runs the joint refinement (report entry ``joint``): the stored
    events' IWE gets sharper, and without a window BA to tell the truth (strides settled along the drifted
    trajectory) the trajectory is no worse than with the single-rotation closure alone; before it, none runs."""
    (t_ev, b_ev), drifted, duration = _drifted_turns()
    joint = _run(t_ev, b_ev, drifted, LOOP, duration=duration)
    alone = _run(t_ev, b_ev, drifted, replace(LOOP, loop_joint_refinement=False), duration=duration)
    runs = [e for e in joint.observer.loops if e.get("joint")]
    assert runs and all(e["joint"]["evaluations"] > 5 and e["joint"]["gain"] > 1.0 for e in runs)
    assert joint.observer.joint_refinements == len(runs) and not any(e.get("joint") for e in alone.observer.loops)
    assert all(e["time"] >= duration / 2.3 for e in runs)  # a full turn travelled first
    ts = np.linspace(0.1, duration - 0.3, 300)
    assert _error(joint, ts, duration, 2.3).mean() < 1.1 * _error(alone, ts, duration, 2.3).mean()


def test_a_joint_refinement_waits_for_a_full_turn_and_the_map_seen_again():
    """The next joint refinement needs a full turn of rotation travelled since the last one and most of the map's
    observed columns observed again since (a pan's wobble adds rotation travelled, not turns)."""
    from ti_cmax.pipelines.backend import SlidingWindowBackend
    from ti_cmax.pipelines.loop_closure import LoopCloser

    be = SlidingWindowBackend(BackendConfig(pano_height=256, backend_min_ev_rate=10000.0, backend_max_window_events=-1),
                              0.0)
    lc = LoopCloser(LOOP, be)
    lc._travel_rec[:, 1], lc._n_travel = (20.0, 7.0), 2  # 7 rad travelled by t = 20 s
    assert lc._joint_due()  # the first one: a full turn travelled
    lc._joint_travel, lc._joint_time, lc.joint_refinements = 0.5, 10.0, 1  # one ran at t = 10 s after 0.5 rad
    cols = lc.age.shape[1]
    lc.age[5, :] = 8.0  # every column observed before it
    lc.age[6, : int(0.6 * cols)] = 15.0  # 60 % of them again since
    assert lc._coverage_since(10.0) == pytest.approx(0.6, abs=0.01) and not lc._joint_due()
    lc.age[6, :] = 15.0  # all of them
    assert lc._joint_due()
    lc._travel_rec[1, 1] = 6.5  # but less than a full turn travelled since the last one
    assert not lc._joint_due()


def test_a_task_in_flight_waits_for_idle_time_while_the_back_end_is_behind():
    """Real time: before_window gives a sliced task in flight its slice, except when the budget says the back-end is
    behind (idle_only); the worker's idle slices still advance it."""
    from ti_cmax.pipelines import loop_closure
    from ti_cmax.pipelines.backend import SlidingWindowBackend

    steps = []
    task = loop_closure._Slices(lambda: [steps.append(k) or lc._slice_point() for k in range(10)])
    cfg = BackendConfig(pano_height=256, backend_min_ev_rate=10000.0, backend_max_window_events=-1)
    lc = loop_closure.LoopCloser(LOOP, SlidingWindowBackend(cfg, 0.0), slice_seconds=0.0)
    lc._task, lc._pending = task, {"kind": "verify", "seconds": 0.0}
    lc.before_window(0.0, 0.2, idle_only=True)
    assert steps == []
    lc.idle_slice()
    assert len(steps) == 1
    lc.before_window(0.1, 0.3)  # a budget of 0 s still runs one slice when not behind
    assert len(steps) == 2
    lc.before_window(0.2, 0.4, idle_only=True)
    assert len(steps) == 2


@pytest.mark.slow
def test_the_joint_refinement_refines_the_start(ti_runtime):
    """With the joint refinement, the start of the trajectory is registered against the map of the later events
    (report entry ``joint.start``; ``joint_refinement.refine_start`` is tested on its own): only the poses of the
    start move. Off (loop_joint_start_span = 0) it does not run."""
    (t_ev, b_ev), drifted, duration = _drifted_turns()
    joined = _run(t_ev, b_ev, drifted, LOOP, duration=duration)
    kept = _run(t_ev, b_ev, drifted, replace(LOOP, loop_joint_start_span=0.0), duration=duration)
    runs = [e["joint"] for e in joined.observer.loops if e.get("joint")]
    assert runs and all(r["start"]["evaluations"] > 3 and r["start"]["events"] > 0 for r in runs)
    assert not any("start" in e.get("joint", {}) for e in kept.observer.loops)
    ts = np.linspace(0.0, 1.0, 21)  # the start moved; the poses after it are those of the run without
    moved = np.degrees(so3.geodesic_angle(joined.spline.evaluate(ts), kept.spline.evaluate(ts)))
    t_end = runs[0]["start"]["t_n"] + LOOP.loop_joint_start_span
    assert moved[ts < 0.1].min() > 1e-4 and moved[ts > t_end + 0.15].max() < 1e-9, moved
