"""The ingest's hot-pixel filter (pipelines/hot_pixels.py): hot and flickering pixels are flagged, the pixels a moving
scene makes fire are not, whatever the motion, the sensor size or the chunking; the start is held back until the first
test; the pipelines drop the flagged pixels' events and report them."""
from dataclasses import replace

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from ti_cmax.config import FrontendConfig
from ti_cmax.errors import InputError
from ti_cmax.events import Events
from ti_cmax.pipelines import hot_pixels as hp
from ti_cmax.pipelines.hot_pixels import HotPixelFilter, isolated_pixels


# ---- synthetic event streams -----------------------------------------------------------------------------------------

def _scene_events(rng, width, height, velocity, duration, edges, points, gain):
    """Events of a scene translating at ``velocity`` (px/s) over the sensor: straight edges (every pixel whose centre
    an edge crosses fires its events-per-crossing times the pixel's gain, spread over the crossing) and sharp points
    (the pixel a point leaves and the one it enters fire at each pixel boundary it crosses)."""
    ys, xs = np.mgrid[0:height, 0:width]
    cx, cy = xs.ravel().astype(float), ys.ravel().astype(float)
    t_all, pix_all = [], []
    speed = float(np.hypot(*velocity))
    for normal, offset, per_crossing in edges:
        nv = float(normal @ velocity)
        if abs(nv) < 1e-9:
            continue
        t_cross = (normal[0] * cx + normal[1] * cy - offset) / nv
        hit = np.flatnonzero((t_cross >= 0) & (t_cross < duration))
        counts = np.rint(per_crossing * gain[hit]).astype(int)
        spread = 1.0 / abs(nv)  # the edge takes this long to cross a pixel
        t_all.append(np.repeat(t_cross[hit], counts) + rng.uniform(-0.5, 0.5, counts.sum()) * spread)
        pix_all.append(np.repeat(hit, counts))
    for start, per_crossing in points:
        steps = int(np.ceil(speed * duration)) + 2
        crossings = []
        for axis in (0, 1):
            v = velocity[axis]
            if abs(v) < 1e-12:
                continue
            first = np.floor(start[axis] + 0.5) + (1 if v > 0 else 0)
            k = first + np.sign(v) * np.arange(steps)
            t_k = (k - 0.5 - start[axis]) / v
            crossings.append(t_k[(t_k >= 0) & (t_k < duration)])
        for t_c in np.sort(np.concatenate(crossings)) if crossings else []:
            before = start + velocity * (t_c - 1e-9)
            after = start + velocity * (t_c + 1e-9)
            for pos in (before, after):
                x, y = (int(np.floor(c + 0.5)) for c in pos)
                if 0 <= x < width and 0 <= y < height:
                    n = int(np.rint(per_crossing * gain[y * width + x]))
                    t_all.append(t_c + rng.uniform(0, 2e-4, n))
                    pix_all.append(np.full(n, y * width + x))
    if not t_all:
        return np.zeros(0), np.zeros(0, int)
    return np.concatenate(t_all), np.concatenate(pix_all)


def _hot_events(rng, pixel, rate, duration, flicker):
    """A hot pixel's events: Poisson at ``rate``; a flickering one fires the same number in bursts (a tenth of each
    0.2 s period)."""
    n = rng.poisson(rate * duration)
    t = rng.uniform(0, duration, n)
    if flicker:
        t = np.floor(t / 0.2) * 0.2 + rng.uniform(0, 0.02, n)
    return t, np.full(n, pixel)


def _as_events(t, pix, width):
    keep = (t >= 0)
    order = np.argsort(t[keep], kind="stable")
    t, pix = t[keep][order], pix[keep][order]
    return Events(t, (pix % width).astype(np.uint16), (pix // width).astype(np.uint16),
                  np.where(np.arange(len(t)) % 2, 1, -1).astype(np.int8))


def _random_chunks(events, rng, max_size):
    i = 0
    while i < len(events):
        n = int(rng.integers(1, max_size))
        yield events[i:i + n]
        i += n


def _spread_pixels(rng, width, height, count):
    """``count`` pixels at least 3 px apart in x or y (two hot pixels side by side shield each other)."""
    chosen: list[tuple[int, int]] = []
    for _ in range(200):
        if len(chosen) == count:
            break
        x, y = int(rng.integers(0, width)), int(rng.integers(0, height))
        if all(max(abs(x - a), abs(y - b)) > 2 for a, b in chosen):
            chosen.append((x, y))
    return [y * width + x for x, y in chosen]


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(seed=st.integers(0, 2**31), width=st.integers(24, 96), height=st.integers(16, 72),
       log_speed=st.floats(np.log(0.5), np.log(3000.0)), angle=st.floats(0, 2 * np.pi),
       n_edges=st.integers(0, 6), n_points=st.integers(0, 25), n_hot=st.integers(0, 4), flicker=st.booleans())
def test_hot_pixels_are_flagged_and_moving_scene_pixels_are_not(seed, width, height, log_speed, angle, n_edges,
                                                                 n_points, n_hot, flicker):
    rng = np.random.default_rng(seed)
    speed = float(np.exp(log_speed))
    velocity = speed * np.array([np.cos(angle), np.sin(angle)])
    duration = float(np.clip(3.0 * (width + height) / speed, 0.5, 3.0))  # slow motions: a few pixels only
    gain = rng.uniform(0.7, 1.3, width * height)  # per-pixel threshold mismatch
    travel = speed * duration
    edges = []
    for _ in range(n_edges):
        a = rng.uniform(0, 2 * np.pi)
        normal = np.array([np.cos(a), np.sin(a)])
        edges.append((normal, rng.uniform(-travel - width - height, width + height), int(rng.integers(1, 7))))
    points = [(rng.uniform([-travel, -travel], [width + travel, height + travel]), int(rng.integers(2, 25)))
              for _ in range(n_points)]
    t, pix = _scene_events(rng, width, height, velocity, duration, edges, points, gain)
    noise = rng.poisson(0.5 * width * height * duration)  # background activity, 0.5 Hz per pixel
    t = np.concatenate([t, rng.uniform(0, duration, noise)])
    pix = np.concatenate([pix, rng.integers(0, width * height, noise)])
    # hot pixels fire far more than any scene pixel: 40 x the busiest one's mean rate, and at least 150 Hz
    scene_peak = np.bincount(pix, minlength=width * height).max() / duration if len(pix) else 0.0
    hot = _spread_pixels(rng, width, height, n_hot)
    for p in hot:
        th, ph = _hot_events(rng, p, max(150.0, 40 * scene_peak) * rng.uniform(1.0, 1.5), duration, flicker)
        t, pix = np.concatenate([t, th]), np.concatenate([pix, ph])
    events = _as_events(t, pix, width)
    filt = HotPixelFilter(width, height, FrontendConfig())
    out = list(filt.filter(_random_chunks(events, rng, 5000)))
    flagged = set(np.flatnonzero(filt.flagged).tolist())
    assert flagged == set(hot)
    kept = Events.concatenate(out)
    for x, y, t_flagged, _ in filt.found:  # from the test that flagged it on, none of its events goes on
        assert not np.any((kept.x == x) & (kept.y == y) & (kept.t >= t_flagged))
    assert len(kept) + filt.events_dropped == len(events)
    assert np.all(np.diff(kept.t) >= 0)


def test_chunking_does_not_change_what_is_flagged_nor_what_passes():
    rng = np.random.default_rng(3)
    width, height = 64, 48
    t, pix = _scene_events(rng, width, height, np.array([40.0, 15.0]), 2.0,
                           [(np.array([0.8, 0.6]), -30.0, 3), (np.array([0.0, 1.0]), -60.0, 4)],
                           [(np.array([5.0, 7.0]), 12)], rng.uniform(0.7, 1.3, width * height))
    for p in (200, 1500):
        th, ph = _hot_events(rng, p, 300.0, 2.0, False)
        t, pix = np.concatenate([t, th]), np.concatenate([pix, ph])
    events = _as_events(t, pix, width)
    results = []
    for chunks in ([events], list(_random_chunks(events, rng, 50)), list(_random_chunks(events, rng, 20000))):
        filt = HotPixelFilter(width, height, FrontendConfig())
        kept = Events.concatenate(list(filt.filter(chunks)))
        results.append((filt.summary(), kept))
    for summary, kept in results[1:]:
        assert summary == results[0][0]
        np.testing.assert_array_equal(kept.t, results[0][1].t)
        np.testing.assert_array_equal(kept.x, results[0][1].x)
    assert results[0][0]["count"] == 2 and results[0][0]["pixels"] == [[200 % width, 200 // width],
                                                                      [1500 % width, 1500 // width]]


def test_the_start_is_held_back_until_the_first_test_and_no_longer():
    """A hot pixel firing from the first event: none of its events goes on; the held start is bounded by
    START_EVENTS_PER_PIXEL events per pixel (a steady scene without hot pixels) and hot_pixel_hold_time."""
    width, height = 40, 30
    rng = np.random.default_rng(0)
    hot = _hot_events(rng, 333, 500.0, 1.0, False)
    background = rng.uniform(0, 1.0, 3000), rng.integers(0, width * height, 3000)
    events = _as_events(np.concatenate([hot[0], background[0]]), np.concatenate([hot[1], background[1]]), width)
    filt = HotPixelFilter(width, height, FrontendConfig())
    released = []
    for chunk in _random_chunks(events, rng, 30):
        out = filt.push(chunk)
        if not released and not out:
            assert filt._holding
        released += out
    kept = Events.concatenate(released + filt.flush())
    assert filt.summary()["pixels"] == [[333 % width, 333 // width]]
    assert not np.any((kept.x == 333 % width) & (kept.y == 333 // width))  # none of its events went on
    assert filt.released_at < events.t[0] + 0.1  # 32 events at 500 Hz
    # a dense scene: released once it holds about one event per pixel (counted per batch of an eighth of them)
    dense = _as_events(np.sort(rng.uniform(0, 1.0, 200_000)), rng.integers(0, width * height, 200_000), width)
    filt = HotPixelFilter(width, height, FrontendConfig())
    first = next(out for chunk in _random_chunks(dense, rng, 100) for out in filt.push(chunk))
    assert len(first) <= (hp.START_EVENTS_PER_PIXEL + 0.125) * width * height + 100
    # a silent one: released after hot_pixel_hold_time
    sparse = _as_events(np.linspace(0, 2.0, 400), rng.integers(0, width * height, 400), width)
    filt = HotPixelFilter(width, height, replace(FrontendConfig(), hot_pixel_hold_time=0.3))
    first = next(out for chunk in _random_chunks(sparse, rng, 5) for out in filt.push(chunk))
    assert 0.3 <= filt.released_at <= 0.3 + hp.COUNT_INTERVAL + 0.01 and first.t[-1] <= filt.released_at


def test_a_pixel_turning_hot_later_is_caught_within_a_block():
    width, height = 48, 32
    rng = np.random.default_rng(5)
    t = np.sort(rng.uniform(0, 4.0, 20_000))
    pix = rng.integers(0, width * height, len(t))
    th = np.sort(rng.uniform(2.0, 4.0, 600))  # from t = 2 s, 300 Hz
    events = _as_events(np.concatenate([t, th]), np.concatenate([pix, np.full(len(th), 700)]), width)
    filt = HotPixelFilter(width, height, FrontendConfig())
    list(filt.filter(_random_chunks(events, rng, 400)))
    (x, y, t_flagged, count), = filt.found
    assert (x, y) == (700 % width, 700 // width)
    # a block ends at the latest when the pixel has fired BLOCK_PEAK_FACTOR x min_events (0.21 s at 300 Hz)
    assert 2.0 < t_flagged < 2.0 + 1.5 * hp.BLOCK_PEAK_FACTOR * FrontendConfig().hot_pixel_min_events / 300.0
    assert filt.events_dropped > 400


def test_switched_off_every_chunk_passes_unchanged():
    events = _as_events(np.linspace(0, 1, 5000), np.full(5000, 7), 10)
    filt = HotPixelFilter(10, 10, replace(FrontendConfig(), hot_pixel_filter=False))
    chunks = [events[:100], events[100:]]
    assert [out for chunk in chunks for out in filt.push(chunk)] == chunks and filt.flush() == []
    assert filt.summary()["count"] == 0 and filt.summary()["enabled"] is False


def test_isolation_rule_counts_the_whole_neighbourhood_and_the_border():
    counts = np.zeros((10, 12), int)
    counts[0, 0] = 40  # a corner: 3 + 5 neighbours within 2 px, all silent
    counts[5, 5], counts[7, 7] = 40, 5  # a neighbour 2 px away with 5 events: 40 < 8 x (5 + 1)
    counts[2, 9] = 15  # below hot_pixel_min_events
    assert isolated_pixels(counts, 8.0, 16).tolist() == [0]
    counts[7, 7] = 4
    assert sorted(isolated_pixels(counts, 8.0, 16).tolist()) == [0, 5 * 12 + 5]


def test_near_the_edge_a_pixel_must_pass_in_two_consecutive_blocks():
    """A sharp point entering the view fires the edge pixel with no neighbour on the sensor, then moves on; a hot
    pixel on the edge keeps firing."""
    width, height = 30, 20
    rng = np.random.default_rng(4)
    background = rng.uniform(0, 3.0, 1000), rng.integers(0, width * height, 1000)
    # the point enters pixel (0, 10) at t = 1 s (40 events), leaves it into (1, 10) at 1.4 s
    point = np.concatenate([1.0 + rng.uniform(0, 2e-4, 40), 1.4 + rng.uniform(0, 2e-4, 80)])
    point_pix = np.concatenate([np.full(80, 10 * width), np.full(40, 10 * width + 1)])
    edge_hot = _hot_events(rng, 5 * width + width - 1, 200.0, 3.0, False)  # (29, 5) on the right edge
    # (15, 10) turns hot at 1.1 s: its 64th event ends a block between the point's two crossings
    late_hot = _hot_events(rng, 10 * width + 15, 400.0, 1.9, False)
    events = _as_events(np.concatenate([background[0], point, edge_hot[0], late_hot[0] + 1.1]),
                        np.concatenate([background[1], point_pix, edge_hot[1], late_hot[1]]), width)
    filt = HotPixelFilter(width, height, FrontendConfig())
    list(filt.filter(_random_chunks(events, rng, 500)))
    assert filt.summary()["pixels"] == [[width - 1, 5], [15, 10]]
    assert 1.1 < filt.found[1][2] < 1.4


@pytest.mark.parametrize("field,value", [("hot_pixel_factor", 1.0), ("hot_pixel_min_events", 1),
                                         ("hot_pixel_hold_time", -0.1)])
def test_config_refuses_rules_out_of_range(field, value):
    from ti_cmax.errors import InputError

    with pytest.raises(InputError, match=field):
        replace(FrontendConfig(), **{field: value})


@pytest.fixture(scope="module")
def slow_pan_with_hot_pixels(ti_runtime):
    """1.5 s DAVIS240C pan starting from rest (under 0.13 rad/s), with 5 hot pixels at 200 Hz: at the start they
    fire as much as a thousand pixels of the scene."""
    from ti_cmax.simulate import SimulatorConfig, simulate_sequence

    return simulate_sequence(SimulatorConfig(scene="bay", trajectory="pan", duration=1.5, turns=0.015, hot_pixels=5,
                                             hot_pixel_rate=200.0, seed=4))


def test_slam_drops_the_hot_pixels_and_follows_the_slow_motion(slow_pan_with_hot_pixels):
    from ti_cmax.config import SlamConfig, update_config
    from ti_cmax.metrics import evaluate_rotations
    from ti_cmax.pipelines.slam import run_slam

    seq = slow_pan_with_hot_pixels
    ev = seq.events
    counts = np.bincount(ev.y.astype(int) * seq.camera.width + ev.x)
    busiest = {(int(i % seq.camera.width), int(i // seq.camera.width))
               for i in np.flatnonzero(counts > 20 * np.median(counts[counts > 0]))}
    assert len(busiest) == 5  # the hot pixels
    on = run_slam(ev, seq.camera, SlamConfig())
    off = run_slam(ev, seq.camera, update_config(SlamConfig(), {"hot_pixel_filter": False}))
    report = on.report["hot_pixels"]
    assert {tuple(p) for p in report["pixels"]} == busiest and report["count"] == 5
    assert max(report["flagged_at"]) < ev.t[0] + 0.3 and report["events_dropped"] > 0.9 * 5 * 200 * 1.5
    assert on.report["events_processed"] == len(ev)
    assert off.report["hot_pixels"] == {**off.report["hot_pixels"], "enabled": False, "count": 0, "events_dropped": 0}
    err_on = evaluate_rotations(seq.groundtruth, on.trajectory).abs_rmse_deg
    err_off = evaluate_rotations(seq.groundtruth, off.trajectory).abs_rmse_deg
    assert err_on < 0.06 and err_off > 4 * err_on  # measured: 0.019 vs 0.265 deg


def test_the_front_end_alone_and_refine_drop_them_too(slow_pan_with_hot_pixels):
    from ti_cmax.config import SlamConfig
    from ti_cmax.pipelines.frontend import estimate_angular_velocity
    from ti_cmax.pipelines.slam import refine

    seq = slow_pan_with_hot_pixels
    half = seq.events.slice_time(seq.events.t[0], seq.events.t[0] + 0.6)
    fe = estimate_angular_velocity(half, seq.camera, FrontendConfig())
    ba = refine(half, seq.camera, seq.groundtruth, SlamConfig())
    assert fe.hot_pixels["count"] == ba.report["hot_pixels"]["count"] == 5
    assert fe.hot_pixels["pixels"] == ba.report["hot_pixels"]["pixels"]
    assert ba.report["events_processed"] == fe.timing["events_processed"] == len(half)


def test_a_stream_of_hot_pixels_alone_is_one_clear_error(ti_runtime):
    from ti_cmax.camera import Camera
    from ti_cmax.config import SlamConfig
    from ti_cmax.errors import InputError
    from ti_cmax.pipelines.slam import run_slam

    camera = Camera(240, 180, 200.0, 200.0, 120.0, 90.0)
    n = 400
    lone = Events(np.linspace(0.0, 0.5, n), np.full(n, 100), np.full(n, 90), np.ones(n))
    with pytest.raises(InputError, match=r"all 400 events came from 1 hot pixel\(s\).*\(100, 90\)"):
        run_slam(lone, camera, SlamConfig())


def test_the_counting_kernel_decides_as_its_numpy_twin(monkeypatch):
    """The filter with its counting kernel and with the kernel's numpy twin in its place: the same pixels flagged at
    the same times, the same events passed on (hot pixels, a held start, chunks across the count checks)."""
    from ti_cmax.kernels.pixel_count import count_pixels_numpy

    rng = np.random.default_rng(11)
    width, height = 64, 48
    t, pix = _scene_events(rng, width, height, np.array([25.0, -10.0]), 1.5,
                           [(np.array([0.6, 0.8]), -20.0, 3)], [(np.array([30.0, 9.0]), 8)],
                           rng.uniform(0.7, 1.3, width * height))
    for p in (130, 2000, 3070):  # 3070 sits at the bottom edge: flagged after two blocks
        th, ph = _hot_events(rng, p, 400.0, 1.5, p == 2000)
        t, pix = np.concatenate([t, th]), np.concatenate([pix, ph])
    events = _as_events(t, pix, width)
    chunks = list(_random_chunks(events, rng, 700))
    results = []
    for twin in (False, True):
        filt = HotPixelFilter(width, height, FrontendConfig())
        if twin:
            def counted(x, y, any_flagged=True, filt=filt):
                keep, peak, dropped = count_pixels_numpy(x, y, width, filt.flagged, filt._counts)
                return (keep if dropped else None), peak, dropped
            monkeypatch.setattr(filt, "_counter", counted)
        kept = Events.concatenate(list(filt.filter(chunks)))
        results.append((filt.summary(), kept))
    (summary, kept), (summary_twin, kept_twin) = results
    assert summary == summary_twin and summary["count"] >= 2 and summary["events_dropped"] > 0
    for f in ("t", "x", "y", "p"):
        np.testing.assert_array_equal(getattr(kept, f), getattr(kept_twin, f))


def test_integer_pixels_off_the_sensor_are_one_clear_error():
    filt = HotPixelFilter(16, 8, FrontendConfig())
    bad = Events(np.array([0.0, 0.1]), np.array([3, 16], np.uint16), np.array([1, 2], np.uint16),
                 np.array([1, -1], np.int8))
    with pytest.raises(InputError, match="x=16, outside the sensor"):
        filt.push(bad)


@pytest.mark.parametrize("shape", [(48, 64), (3, 4), (5, 5), (1, 7)])
def test_neighbourhood_max_is_the_max_over_the_zero_padded_neighbourhood(shape):
    rng = np.random.default_rng(sum(shape))
    counts = rng.poisson(3, shape).astype(np.int32)
    rows, cols = np.divmod(np.arange(counts.size), shape[1])
    for radius in (1, 2):
        padded = np.pad(counts, radius)
        expected = np.zeros(counts.size, np.int32)
        for dy in range(-radius, radius + 1):
            for dx in range(-radius, radius + 1):
                if dx or dy:
                    expected = np.maximum(expected, padded[rows + radius + dy, cols + radius + dx])
        np.testing.assert_array_equal(hp.neighbourhood_max(counts, rows, cols, radius), expected)
