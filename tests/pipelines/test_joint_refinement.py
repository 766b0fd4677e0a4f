"""Joint refinement over revisits (pipelines/joint_refinement.py): a later visit's error is pulled onto the map of
the earlier visit, the sampling keeps strides in proportion, large panoramas use a coarser level."""
import numpy as np
import pytest

from ti_cmax import so3
from ti_cmax.config import BackendConfig
from ti_cmax.spline import SO3Spline
from ti_cmax.pipelines.joint_refinement import (
    _interpolation, batch_size, map_level, refine_jointly, refine_start, sample_chunks,
)

from test_loop_closure import _events, _pan, _spline

DURATION, TURNS = 4.0, 2.0  # s, pan turns: the second turn revisits the first
BUMP = np.radians(1.0)  # error of the second turn at its middle (zero at its ends), about BUMP_AXIS
BUMP_AXIS = np.array([1.0, 0.4, 0.2]) / np.linalg.norm([1.0, 0.4, 0.2])


def _bumped(t):
    """The pan with an error in its second turn only: a drift that a loop closure left between the visits."""
    t = np.asarray(t, dtype=float)
    phase = np.clip((t - DURATION / TURNS) / (DURATION / TURNS), 0.0, 1.0)
    return so3.exp(np.outer(BUMP * np.sin(np.pi * phase), BUMP_AXIS)) @ _pan(t, DURATION, TURNS)


def _chunks(t, b, stride=0.1):
    edges = np.arange(0, DURATION + 1e-9, stride)
    out = []
    for a, z in zip(edges[:-1], edges[1:]):
        m = (t >= a) & (t < z)
        out.append((t[m], b[m], 1.0, float(a), True))
    return out


def test_sample_keeps_each_stride_in_proportion_to_the_events_it_stands_for():
    rng = np.random.default_rng(0)
    chunks = [(np.sort(rng.uniform(k, k + 1, n)), rng.normal(size=(n, 3)).astype(np.float32), w, float(k), True)
              for k, (n, w) in enumerate([(1000, 1.0), (1000, 4.0), (500, 2.0)])]
    t, b, frac = sample_chunks(chunks, 1500)
    assert len(t) == len(b) <= 1500 + 3 and frac == pytest.approx(len(t) / 6000, rel=1e-3)
    per = np.histogram(t, bins=[0, 1, 2, 3])[0]
    np.testing.assert_allclose(per / per.sum(), [1 / 6, 4 / 6, 1 / 6], atol=0.01)  # 1000, 4000, 1000 stood for
    assert np.all(np.diff(t) >= 0)
    t_all, _, frac_all = sample_chunks(chunks, 10**6)  # above what is stored: every stride whole
    assert len(t_all) == 2500 and frac_all == pytest.approx(2500 / 6000)


def test_map_level_brings_large_panoramas_to_at_most_2048_columns():
    assert map_level(2048, 1024) == 1
    assert map_level(4096, 2048) == 2
    assert map_level(6000, 3000) == 4
    assert map_level(4097, 2048) == 1  # no level divides it: full size


@pytest.mark.slow
def test_a_later_visit_is_pulled_onto_the_earlier_visits_map(ti_runtime):
    t, b = _events(seed=4, duration=DURATION, turns=TURNS, rate=60_000)
    spline = _spline(_bumped, duration=DURATION)
    cfg = BackendConfig(pano_height=512)
    first = int(np.searchsorted(spline.knot_times(), DURATION / TURNS))  # the second turn's poses are free
    last = spline.num_control - 1
    ts = np.linspace(DURATION / TURNS + 0.1, DURATION - 0.1, 200)

    def error(spl):
        return np.degrees(so3.geodesic_angle(spl.evaluate(ts), _pan(ts, DURATION, TURNS)))

    before = error(spline)
    x, info = refine_jointly(spline, _chunks(t, b), first, last, cfg, 1024, 512, max_events=200_000,
                             iterations=30, fine_iterations=15, coarse_spacing=0.5, max_step=0.1)
    refined = spline.copy()
    refined.control_R[first:last + 1] = so3.exp(x) @ refined.control_R[first:last + 1]
    after = error(refined)
    assert info["gain"] > 1.0 and info["evaluations"] > 5 and info["poses"] == last - first + 1
    assert before.max() > 0.9 and after.max() < 0.3 * before.max(), (before.max(), after.max())
    # the first turn's poses stayed: they anchor the world frame
    assert np.all(np.abs(x) <= 0.1 + 1e-12)


def test_a_batch_spans_half_a_map_pixel_of_motion_at_the_fastest_rotation():
    """Sampled events per batch: those arriving while the fastest rotation moves the map half a pixel (an evaluation
    costs about one spline evaluation per batch), never fewer than the back-end's batch span at the sampled rate."""
    speed, dt = 2.0, 0.05  # rad/s of a pan, knot spacing
    spline = SO3Spline(3, -dt, dt, so3.exp(np.outer(speed * dt * np.arange(84), [0.0, 1.0, 0.0])))
    times = np.linspace(0.0, 4.0, 40_001)  # 10 000 sampled events per second
    expected = int(0.5 * 2 * np.pi / 1024 / speed * 10_000)
    last = spline.num_control - 1
    assert expected == 15 and batch_size(spline, 0, last, times, 1024, least=1.0) == expected
    assert batch_size(spline, 0, last, times, 256, least=1.0) == int(4 * 0.5 * 2 * np.pi / 1024 / speed * 10_000)
    assert batch_size(spline, 0, last, times, 1024, least=40.0) == 40
    still = SO3Spline(3, -dt, dt, np.broadcast_to(np.eye(3), (84, 3, 3)).copy())
    assert batch_size(still, 0, last, times, 1024, least=3.0) == len(times)  # no motion: one batch


def test_held_mean_redistributes_the_errors_without_turning_the_span(ti_runtime):
    """``hold_mean``: the increments at the nodes average zero (the rotation common to them is left to the window
    BA: with only the first pose fixed, the first instants' few events tie it weakly); free, the same second-turn
    error is undone partly by a common turn of its nodes."""
    t, b = _events(seed=4, duration=DURATION, turns=TURNS, rate=20_000)
    spline = _spline(_bumped, duration=DURATION)
    cfg = BackendConfig(pano_height=256)
    knots = spline.knot_times()
    first, last = int(np.searchsorted(knots, DURATION / TURNS)), spline.num_control - 1
    interp = _interpolation(knots[first:last + 1], 0.5)  # poses from the nodes' increments

    def node_mean(hold):
        x, _ = refine_jointly(spline, _chunks(t, b), first, last, cfg, 512, 256, max_events=60_000, iterations=8,
                              coarse_spacing=0.5, max_step=0.1, hold_mean=hold)
        return np.degrees(np.linalg.lstsq(interp, x, rcond=None)[0].mean(axis=0))

    held, free = node_mean(True), node_mean(False)
    assert np.linalg.norm(held) < 1e-6 and np.dot(free, BUMP_AXIS) < -0.2, (held, free)  # free: undoes the bump


def test_the_setup_pauses_between_its_steps(ti_runtime, monkeypatch):
    """Sliced (real time), the refinement pauses before sampling the stored events, before building its problem and
    before every evaluation: no step of it holds the back-end longer than one of them."""
    import ti_cmax.pipelines.joint_refinement as J

    t, b = _events(seed=5, duration=DURATION, turns=TURNS, rate=5_000)
    spline = _spline(_bumped, duration=DURATION)
    steps = []
    sample, problem = J.sample_chunks, J.PanoIWE
    monkeypatch.setattr(J, "sample_chunks", lambda *a, **k: steps.append("sample") or sample(*a, **k))
    monkeypatch.setattr(J, "PanoIWE", lambda *a, **k: steps.append("problem") or problem(*a, **k))
    first = int(np.searchsorted(spline.knot_times(), DURATION / TURNS))
    refine_jointly(spline, _chunks(t, b), first, spline.num_control - 1, BackendConfig(pano_height=256), 512, 256,
                   max_events=20_000, iterations=2, coarse_spacing=0.5, max_step=0.1,
                   slice_point=lambda: steps.append("pause"))
    assert steps[:2] == ["pause", "sample"] and steps[steps.index("problem") - 1] == "pause", steps
    assert steps.index("sample") + 1 < steps.index("problem") and steps[steps.index("problem") + 1] == "pause", steps


START_ERROR = np.radians(0.5)  # the start's error, about BUMP_AXIS: whole before 0.15 s, none from 0.45 s on


def _started_off(t):
    """The pan with an error of its first instants only (a first window whose young map set it off): the later
    poses are right among themselves, so aligned at the start the whole trajectory would carry it."""
    t = np.asarray(t, dtype=float)
    ramp = np.clip((0.45 - t) / 0.3, 0.0, 1.0)
    return so3.exp(np.outer(START_ERROR * ramp, BUMP_AXIS)) @ _pan(t, DURATION, TURNS)


def test_the_start_is_registered_against_the_map_of_the_later_events(ti_runtime):
    """The poses of the start, refined against the map the later events build, join the rest: the start's rotation
    relative to a later pose comes close to the truth. The poses before the first window's worth of events move as
    one block (a still start's few events would turn each of them at random)."""
    t, b = _events(seed=6, duration=DURATION, turns=TURNS, rate=150_000)
    spline = _spline(_started_off, duration=DURATION)
    cfg = BackendConfig(pano_height=256)
    rate = len(t) / DURATION
    min_events = 0.1 * rate  # reached at about 0.1 s

    def start_error(spl):  # R(t) relative to R(2 s), against the truth's, at the start (deg)
        ts = np.array([0.1, 0.15])
        rel = spl.evaluate(ts) @ spl.evaluate(2.0)[0].T
        truth = _pan(ts, DURATION, TURNS) @ _pan(np.array([2.0]), DURATION, TURNS)[0].T
        return np.degrees(so3.geodesic_angle(rel, truth))

    before = start_error(spline)
    y, info = refine_start(spline, _chunks(t, b), min_events, 0.1, 0.5, cfg, 512, 256, max_events=100_000,
                           iterations=20, max_step=0.1)
    refined = spline.copy()
    refined.control_R[:len(y)] = so3.exp(y) @ refined.control_R[:len(y)]
    after = start_error(refined)
    assert before.min() > 0.45 and after.max() < 0.3 * before.min(), (before, after)
    assert 0.08 < info["t_n"] < 0.12 and info["evaluations"] > 3
    knots = spline.knot_times()
    block = knots[:len(y)] <= info["t_n"]
    assert block.sum() >= 3 and np.allclose(y[block], y[0], atol=1e-12)  # before t_n: one increment
    assert np.allclose(y[knots[:len(y)] >= info["t_n"] + 0.5 - 1e-9], 0.0)  # from t_n + span on: none
