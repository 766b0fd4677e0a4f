"""SMT baseline (pipelines/baselines/smt.py): EKF-SMT / PF-SMT accuracy on a short simulated sequence with IMU,
seeded reproducibility, tracking loss reported as a status, the mapping EKF through the SMT path on a moving edge."""
import numpy as np
import pytest

from ti_cmax import so3
from ti_cmax.camera import Camera
from ti_cmax.config import load_config
from ti_cmax.errors import InputError
from ti_cmax.events import Events
from ti_cmax.metrics import evaluate_rotations
from ti_cmax.pipelines.baselines.smt import SmtConfig, run_smt, run_smt_ekf
from ti_cmax.pipelines.workflows.grayscale import GrayscaleConfig
from ti_cmax.trajectory import Trajectory


@pytest.fixture(scope="module")
def city(ti_runtime):
    """1.5 s DAVIS240C city, peak 2 rad/s, biased gyro (~1.2 M events): 0.5 s IMU bootstrap, 1 s of tracking."""
    from ti_cmax.simulate import SimulatorConfig, simulate_sequence

    return simulate_sequence(SimulatorConfig(scene="city", duration=1.5, max_angular_velocity=2.0, seed=1,
                                             gyro_bias_std=0.03))


def _run(seq, tracker, config=None, events=None):
    return run_smt(seq.events if events is None else events, seq.camera, config or SmtConfig(), tracker=tracker,
                   imu=seq.imu, groundtruth=seq.groundtruth, contrast_threshold=seq.config.contrast_threshold)


@pytest.mark.slow
def test_ekf_smt_tracks_with_imu_bootstrap(city):
    """Defaults, loss checks on (the fixture was declared by an earlier session; with the random-walk EKF and
    per-event measurements this run was declared lost at 1.39 s, 1.5 deg up to there, 2.6 deg over the whole run
    without the check)."""
    res = run_smt_ekf(city.events, city.camera, SmtConfig(), imu=city.imu, groundtruth=city.groundtruth,
                      contrast_threshold=0.2)
    rep = res.report
    assert rep["status"] == "ok" and rep["lost_at"] is None
    assert rep["bootstrap_source"] == "imu" and rep["events_processed"] == len(city.events)
    # the map gain is calibrated on the bootstrap's last 0.1 s (it was silently 1 when the bootstrap filled the
    # first streamed piece: EKF-SMT then drifted 2-20 times more on the benchmark sequences)
    assert 1.02 < rep["map_gain"] < 1.6, rep["map_gain"]
    assert rep["us_per_event"] > 0 and rep["parameters"]["tracker"] == "ekf"
    assert res.trajectory.t_end > 1.45
    err = evaluate_rotations(city.groundtruth, res.trajectory)
    assert err.abs_rmse_deg < 3.0, err.abs_rmse_deg  # 1.48 measured
    # the grayscale map is an 8-bit image with content
    img = res.map.to_uint8()
    assert img.shape == (512, 1024) and img.max() > img.min()


@pytest.mark.slow
def test_pf_smt_tracks_and_is_reproducible(city):
    res = _run(city, "pf")
    rep = res.report
    # the particle filter may lose track on this sequence (it did once its velocity error exceeded ~0.5 rad/s at
    # 1.3 s: 0.8 -> 5.9 deg in 0.2 s); what it returns must be accurate and cover most of the tracking time
    assert rep["status"] == "ok" or rep["lost_reason"], rep
    assert res.trajectory.t_end > 1.0
    err = evaluate_rotations(city.groundtruth, res.trajectory)
    assert err.abs_rmse_deg < 6.0, err.abs_rmse_deg
    # same seed, same result; another seed, another result (0.5 s bootstrap + 0.15 s of tracking)
    short = city.events.slice_time(0.0, 0.65)
    a = _run(city, "pf", events=short)
    b = _run(city, "pf", events=short)
    c = _run(city, "pf", SmtConfig(seed=7), events=short)
    np.testing.assert_array_equal(a.trajectory.R, b.trajectory.R)
    assert not np.array_equal(a.trajectory.R, c.trajectory.R)
    assert a.report["resamples"] > 0


@pytest.mark.slow
@pytest.mark.parametrize("scene,seed", [("bicycle", 0), ("bay", 1)])
def test_ekf_smt_never_returns_a_silently_bad_trajectory(ti_runtime, scene, seed):
    """Simulator defaults (peak 5 rad/s), the first two seeds, two textures: declared before any run, not picked
    from results (the duration was raised from 1.2 to 2 s because at 1.2 s neither run drifted). Without the
    consistency check EKF-SMT drifted to 9-17 deg RMSE with status "ok" on 2-2.5 s sequences like these (bay
    seed 1: 17 deg; measured 0.87 deg up to lost_at 1.28 s with the check; bicycle seed 0: ok, 0.28 deg, with
    and without); whatever it returns (whole sequence or up to lost_at) must be accurate."""
    from ti_cmax.simulate import SimulatorConfig, simulate_sequence

    seq = simulate_sequence(SimulatorConfig(scene=scene, duration=2.0, seed=seed))
    res = _run(seq, "ekf")
    rep = res.report
    assert rep["status"] in ("ok", "lost") and rep["consistency"]["checks"] > 0
    if rep["status"] == "lost":
        assert rep["lost_reason"] and rep["lost_at"] >= rep["bootstrap_end"]
    if res.trajectory.t_end - res.trajectory.t_start > 0.55:  # enough poses to score (1 s relative pairs aside)
        err = evaluate_rotations(seq.groundtruth, res.trajectory)
        assert err.abs_rmse_deg < 3.0, (err.abs_rmse_deg, rep["status"], rep["lost_at"])


@pytest.mark.slow
@pytest.mark.parametrize("scene,seed", [("street", 301), ("town", 302), ("bicycle", 311)])
def test_ekf_smt_tracks_declared_sequences(ti_runtime, scene, seed):
    """Simulator defaults (DAVIS240C, random motion up to 5 rad/s), 1.5 s, seeds declared before the first run
    EKF-SMT with the defaults must track to the end (status ok), accurately."""
    from ti_cmax.simulate import SimulatorConfig, simulate_sequence

    seq = simulate_sequence(SimulatorConfig(scene=scene, duration=1.5, seed=seed))
    res = _run(seq, "ekf")
    rep = res.report
    assert rep["status"] == "ok", (rep["lost_at"], rep["lost_reason"])
    assert res.trajectory.t_end > 1.45
    err = evaluate_rotations(seq.groundtruth, res.trajectory)
    assert err.abs_rmse_deg < 3.0, err.abs_rmse_deg


@pytest.mark.slow
def test_ekf_smt_tracks_fast_angular_acceleration(ti_runtime):
    """Random motion up to 5 rad/s with frequencies up to 3 Hz instead of 1.5 (angular accelerations up to about
    twice those of the benchmark suite), DAVIS240C bay, 1.5 s, seed 303, declared before
    the first run, for the constant-acceleration state (module doc), which must track it to the end."""
    from ti_cmax.simulate import SimulatorConfig, simulate_sequence

    seq = simulate_sequence(SimulatorConfig(scene="bay", duration=1.5, seed=303, random_frequency_max=3.0))
    res = _run(seq, "ekf")
    rep = res.report
    assert rep["parameters"]["motion_model"] == "constant_acceleration"
    assert rep["status"] == "ok", (rep["lost_at"], rep["lost_reason"])
    err = evaluate_rotations(seq.groundtruth, res.trajectory)
    assert err.abs_rmse_deg < 3.0, err.abs_rmse_deg


@pytest.mark.slow
def test_textureless_stretch_is_reported_lost(ti_runtime, tmp_path):
    """DVS128 panning one full turn in 3 s, with background noise, over the procedural city panorama made flat over
    the 120 deg of longitude behind the start: the view holds texture until about 1 s and is wholly flat from about
    1.3 s (the sensor sees ~64 deg), where nothing tells the motion. EKF-SMT must track the textured part accurately,
    then end with status "lost" and a lost_at inside the flat stretch (not a silent drift, not a traceback).
    The flat stretch is wider than the view (120 deg against ~64), so no part of it shows texture."""
    import imageio.v3 as iio

    from ti_cmax.simulate import SimulatorConfig, simulate_sequence
    from ti_cmax.simulate.scenes import procedural_scene

    img = procedural_scene("city", 512, seed=0).astype(float)
    img = (img - img.min()) / (img.max() - img.min())
    lon = (np.arange(img.shape[1]) + 0.5) / img.shape[1] * 360.0 - 180.0
    img[:, np.abs(lon) > 120.0] = 0.5  # flat around the back (longitude 180)
    path = tmp_path / "pano.png"
    iio.imwrite(path, (img * 255).astype(np.uint8))
    seq = simulate_sequence(SimulatorConfig(image=str(path), sensor="DVS128", trajectory="pan", duration=3.0,
                                            noise_rate=1.0, seed=3))
    res = _run(seq, "ekf")
    rep = res.report
    assert rep["status"] == "lost" and rep["lost_reason"], rep
    # the flat stretch reaches the view's centre at 1.0 s; its far side leaves the view at about 2.3 s
    assert 1.0 < rep["lost_at"] < 2.3, rep["lost_at"]
    assert res.trajectory.t_end <= rep["lost_at"] + 1e-9
    err = evaluate_rotations(seq.groundtruth, res.trajectory)
    assert err.abs_rmse_deg < 1.0, err.abs_rmse_deg


@pytest.mark.slow
def test_pure_noise_is_reported_lost_not_raised(ti_runtime):
    """Background-activity events only: no map worth the name, tracking must end with status lost."""
    cam = Camera.ideal(64, 48, 60.0)
    rng = np.random.default_rng(0)
    n = 300_000
    t = np.sort(rng.uniform(0.0, 1.0, n))
    ev = Events(t, rng.integers(0, 64, n).astype(np.uint16), rng.integers(0, 48, n).astype(np.uint16),
                rng.choice(np.array([-1, 1], np.int8), n))
    gt_t = np.linspace(0.0, 1.0, 1001)
    gt = Trajectory(gt_t, so3.exp(np.outer(gt_t, [0.1, 1.0, 0.2])))
    for tracker in ("ekf", "pf"):
        res = run_smt(ev, cam, SmtConfig(bootstrap_seconds=0.3, mapping=GrayscaleConfig(pano_height=256)),
                      tracker=tracker, groundtruth=gt, contrast_threshold=0.2)
        rep = res.report
        assert rep["status"] == "lost", rep
        assert rep["lost_reason"] and rep["bootstrap_end"] <= rep["lost_at"] < 1.0
        assert res.trajectory.t_end <= rep["lost_at"] + 1e-9
        assert rep["events_processed"] < n


def test_needs_imu_or_groundtruth_to_bootstrap(ti_runtime):
    cam = Camera.ideal(32, 24, 60.0)
    ev = Events(np.linspace(0, 0.1, 100), np.zeros(100, np.uint16), np.zeros(100, np.uint16), np.ones(100, np.int8))
    with pytest.raises(InputError):
        run_smt(ev, cam, SmtConfig())


def test_config_loads_with_nested_mapping_keys():
    cfg = load_config(SmtConfig, None, ["tracker=pf", "num_particles=50", "mapping.pano_height=256",
                                        "max_updates_per_pixel=3"])
    assert cfg.tracker == "pf" and cfg.num_particles == 50
    assert cfg.mapping.pano_size == (512, 256) and cfg.mapping.max_updates_per_pixel == 3
    assert cfg.mapping.outlier_distance_px == 10.0
    with pytest.raises(InputError):
        load_config(SmtConfig, None, ["tracker=kalman"])
    with pytest.raises(InputError):
        load_config(SmtConfig, None, ["num_particles=0"])


@pytest.mark.parametrize("settings, expected", [
    ({"tracker": "pf"}, {"pf_loglik"}),
    ({"tracker": "ekf"}, {"ekf_track": (9, True)}),
    ({"tracker": "ekf", "motion_model": "constant_velocity", "reference": "pose"}, {"ekf_track": (6, False)}),
    ({"tracker": "ekf", "motion_model": "random_walk"}, {"ekf_track": (6, False)}),
])
def test_warm_up_compiles_only_the_trackers_kernels(monkeypatch, settings, expected):
    """A run compiles the kernels it launches before it is timed, and no other (PF-SMT without the filter,
    EKF-SMT with its state size and kind of reference only): each EKF variant costs seconds to compile."""
    from ti_cmax.pipelines.baselines import smt as smt_module

    calls = {}
    monkeypatch.setattr(smt_module.km, "warm_up", lambda dtype: None)
    for name in ("select_references", "ekf_accumulate", "pf_loglik"):
        monkeypatch.setattr(smt_module.ks, name, lambda *a, _n=name, **k: calls.setdefault(_n, True))

    def track(*args, state_a=None, **kwargs):
        calls["ekf_track"] = (args[27].shape[1], args[28])  # state_P, velocity_reference

    monkeypatch.setattr(smt_module.ks, "ekf_track", track)
    smt_module._warm_up(np.float32, SmtConfig(**settings))
    assert calls.pop("select_references") and calls.pop("ekf_accumulate")
    assert calls == (expected if isinstance(expected, dict) else {k: True for k in expected})


def test_ekf_acceleration_steps_are_per_batch_not_per_second(monkeypatch):
    """The acceleration's random-walk step is acceleration_step_std per batch whatever the batch lasts (module doc):
    the kernel gets the jerk intensity step / sqrt(mean batch duration of the call), so batches 4x shorter (a 4x
    higher event rate) double it; acceleration_step_std = 0 keeps angular_jerk_std per second."""
    from types import SimpleNamespace

    from ti_cmax.pipelines.baselines import smt as smt_module

    seen = []

    def fake_track(*args, **kwargs):
        seen.append(trk.q_jerk)
        return np.zeros((args[4] - args[3], 7))

    monkeypatch.setattr(smt_module.ks, "ekf_track", fake_track)
    mapper = SimpleNamespace(gradient=None, covariance=None, updates=None,
                             config=SimpleNamespace(outlier_distance_px=10.0))
    mids = np.concatenate([np.arange(11) * 4e-4, 4e-3 + np.arange(1, 11) * 1e-4])  # 400 us, then 100 us batches
    ctx = SimpleNamespace(mids=mids, mapper=mapper, **{k: None for k in (
        "hist", "hist64", "batch_size", "bearings", "pix", "pol", "refs", "ref_uv", "ref_n", "contrast", "sigma",
        "min_disp", "max_lat", "ref_src", "max_events", "position_var", "max_len")})
    cfg = SmtConfig(acceleration_step_std=10.0)  # the default (module doc)
    assert cfg.motion_model == "constant_acceleration"
    trk = smt_module.EkfTracker(np.eye(3), cfg, None)
    trk.run(1, 11, ctx)
    trk.run(11, 21, ctx)
    step = cfg.acceleration_step_std
    np.testing.assert_allclose(seen, [step / np.sqrt(4e-4), step / np.sqrt(1e-4)], rtol=1e-9)
    assert trk.jerk_used == seen
    seen.clear()
    trk = smt_module.EkfTracker(np.eye(3), SmtConfig(acceleration_step_std=0.0), None)
    trk.run(11, 21, ctx)
    assert seen == [SmtConfig().angular_jerk_std] and trk.jerk_used == []


@pytest.mark.slow
def test_segments_longer_than_two_map_pixels_are_not_measurements(city, monkeypatch):
    """EKF-SMT: segments longer than max_segment_px (2 map px by default) restart without a measurement, in the
    bootstrap's selection (gain calibration) and in the EKF's (module doc: their increments are over-predicted, and
    the segment's length, through its age, turned that into a spurious acceleration that lost held-out bicycle 244
    at 2.88 s). Both kernels must get the gate; a gate above the mapper's outlier distance leaves that distance."""
    from ti_cmax.pipelines.baselines import smt as smt_module

    seen = {"select": [], "track": []}
    select, track = smt_module.ks.select_references, smt_module.ks.ekf_track

    def spy_select(*args, **kwargs):
        if len(args[0]) > 2:  # not the compile warm-up's 2 poses
            seen["select"].append(args[11])
        return select(*args, **kwargs)

    def spy_track(*args, **kwargs):
        if len(args[0]) > 2:
            seen["track"].append(args[17])
        return track(*args, **kwargs)

    monkeypatch.setattr(smt_module.ks, "select_references", spy_select)
    monkeypatch.setattr(smt_module.ks, "ekf_track", spy_track)
    short = city.events.slice_time(0.0, 0.6)
    assert SmtConfig().max_segment_px == 2.0
    res = _run(city, "ekf", events=short)
    assert res.report["parameters"]["max_segment_px"] == 2.0
    assert seen["select"] and seen["track"] and set(seen["select"]) | set(seen["track"]) == {2.0}
    seen["select"].clear()
    seen["track"].clear()
    _run(city, "ekf", SmtConfig(max_segment_px=50.0), events=short)
    assert set(seen["select"]) | set(seen["track"]) == {SmtConfig().mapping.outlier_distance_px}
    # PF-SMT keeps the mapper's outlier distance (it has no acceleration state; module doc)
    seen["select"].clear()
    _run(city, "pf", events=city.events.slice_time(0.0, 0.52))
    assert seen["select"] and set(seen["select"]) == {SmtConfig().mapping.outlier_distance_px}


# --- the mapping EKF through the SMT path: a ramp edge swept by a panning camera --------------------------------
W, H = 256, 128
A, S, C = 1.5, 15.0, 0.1  # log intensity M = A clip((u - U0) / S, -1, 1), threshold C
U0 = W / 2 + 10.0
OMEGA, T_END = 0.5, 2.0  # rad/s about the camera y axis: map u moves at W OMEGA / 2 pi px/s


def _edge_events(cam):
    """Exact level-crossing events of every pixel (u(t) = u_b + s t, M monotone in u: positive events only)."""
    b = cam.bearing_lut.astype(np.float64)
    u_b = W / 2 + W * np.arctan2(b[:, 0], b[:, 2]) / (2 * np.pi)
    s = W * OMEGA / (2 * np.pi)
    m0 = A * np.clip((u_b - U0) / S, -1, 1)
    m1 = A * np.clip((u_b + s * T_END - U0) / S, -1, 1)
    ts, pix = [], []
    for k in range(1, int(2 * A / C) + 2):
        level = m0 + k * C
        fire = level <= m1
        u_cross = U0 + S * level[fire] / A
        ts.append((u_cross - u_b[fire]) / s)
        pix.append(np.flatnonzero(fire))
    t, pix = np.concatenate(ts), np.concatenate(pix)
    order = np.argsort(t, kind="stable")
    t, pix = t[order], pix[order]
    return Events(t, (pix % cam.width).astype(np.uint16), (pix // cam.width).astype(np.uint16),
                  np.ones(len(t), np.int8))


def test_mapping_path_converges_to_edge_gradient(ti_runtime):
    cam = Camera.ideal(40, 30, 60.0)
    ev = _edge_events(cam)
    assert len(ev) > 5000
    gt_t = np.linspace(0, T_END, 401)
    gt = Trajectory(gt_t, so3.exp(np.outer(gt_t * OMEGA, [0.0, 1.0, 0.0])))
    cfg = SmtConfig(bootstrap_seconds=T_END + 1, mapping=GrayscaleConfig(pano_height=H, visit_gap=0.0,
                                                                         max_updates_per_pixel=0))
    res = run_smt(ev, cam, cfg, groundtruth=gt, contrast_threshold=C)
    assert res.report["status"] == "ok" and res.report["bootstrap_source"] == "groundtruth"
    g = res.map.gradient
    cols = np.arange(W)
    ramp = (cols > U0 - S + 2) & (cols < U0 + S - 2)
    upd = res.map.stats["updates"]
    assert upd > 0.8 * len(ev) - cam.width * cam.height
    visited = res.map.visited & ramp[None, :]
    assert visited.sum() > 200
    med = np.median(g[visited], axis=0)
    np.testing.assert_allclose(med, [A / S, 0.0], atol=0.05 * A / S)
    # flat parts never fire: gradient stays at zero there
    flat = (cols < U0 - S - 3) | (cols > U0 + S + 3)
    assert np.all(g[:, flat] == 0)


def test_registry_adapter_returns_baseline_result(city):
    from ti_cmax.pipelines.baselines import BaselineConfig
    from ti_cmax.pipelines.baselines.smt import smt_ekf_baseline

    short = city.events.slice_time(0.0, 0.7)
    res = smt_ekf_baseline(short, city.camera, BaselineConfig(), city.imu, contrast_threshold=0.2)
    assert res.report["status"] == "ok" and res.report["method"] == "smt-ekf"
    assert res.report["us_per_event"]["frontend"] > 0
    assert res.map.dtype == np.uint8 and res.map.shape == (512, 1024)
    assert res.trajectory.t_end > 0.65


# --- motion consistency: the events judge the tracker's angular velocity ---------------------------------------
def _feed_check(check, seq, times, poses, stop):
    """Feed a MotionConsistencyCheck new events and poses in 0.1 s pieces from 0.3 s, like the tracker feeds it, up
    to the first failure (returned: the start of the failing run; None if none by ``stop``)."""
    fed = 0.3
    for t_done in np.arange(0.4, stop, 0.1):
        e0, e1 = np.searchsorted(seq.events.t, [fed, t_done])
        p0, p1 = np.searchsorted(times, [fed, t_done])
        failed_from = check.update(seq.events[e0:e1], times[p0:p1], poses[p0:p1], float(t_done))
        fed = t_done
        if failed_from is not None:
            return failed_from
    return None


def test_consistency_check_passes_truth_and_flags_a_velocity_error(city):
    """Ground-truth poses are consistent all along; the same poses with 2 rad/s added about the camera x axis
    from t = 0.9 s fail, and the failing run starts at that time, not before."""
    from ti_cmax.pipelines.baselines.consistency import MotionConsistencyCheck

    times = np.arange(0.0, 1.5, 0.002)
    truth = city.groundtruth.at(times)
    extra = np.clip(times - 0.9, 0.0, None) * 2.0
    wrong = truth @ so3.exp(np.outer(extra, [1.0, 0.0, 0.0]))  # right (camera-frame) perturbation
    results = {}
    for name, poses in (("truth", truth), ("wrong", wrong)):
        check = MotionConsistencyCheck(city.camera, 0.3, 0.05, 0.04, 0.9, 2)
        results[name] = (_feed_check(check, city, times, poses, 1.5), check.summary())
    failed, summary = results["truth"]
    assert failed is None and summary["checks"] >= 20
    assert summary["min_ratio"] > 0.95, summary
    failed, summary = results["wrong"]
    assert failed is not None and 0.85 <= failed <= 1.0, (failed, summary)
    assert summary["min_ratio"] < 0.8


@pytest.mark.slow
def test_streaming_chunks_give_the_same_tracking(city):
    """Chunks of 60k events (20 per second of this sequence) instead of 1M: between chunks only per-pixel state
    is carried, so the result matches up to the map-update timing at chunk ends."""
    short = city.events.slice_time(0.0, 1.0)
    whole = _run(city, "ekf", events=short)
    chunked = _run(city, "ekf", SmtConfig(chunk_events=60_000), events=iter([short[i:i + 25_000] for i in range(0, len(short), 25_000)]))
    assert chunked.report["status"] == whole.report["status"] == "ok"
    assert chunked.report["events_processed"] == whole.report["events_processed"] == len(short)
    np.testing.assert_allclose(chunked.trajectory.t, whole.trajectory.t)
    diff = np.degrees(so3.geodesic_angle(chunked.trajectory.R, whole.trajectory.R))
    assert diff.max() < 0.2, diff.max()
    err = evaluate_rotations(city.groundtruth, chunked.trajectory)
    assert err.abs_rmse_deg < 3.0


@pytest.mark.slow
def test_slow_drift_is_caught_where_the_contrast_ratio_is_blind(city):
    """Slow-drift test (consistency.py): ground-truth poses pass; a steady 0.2 rad/s error about the camera x axis
    from t = 0.6 s keeps the contrast ratios above 0.9 (the ratio rule alone never fails it; 0.3 rad/s it does, late)
    but drifts ~2.3 deg per 0.2 s part, so the drift test fails it, its horizon starting where the error starts; the
    same error for 0.2 s only (a transient, as at a turn-back) passes."""
    from ti_cmax.pipelines.baselines.consistency import MotionConsistencyCheck

    times = np.arange(0.0, 1.5, 0.002)
    truth = city.groundtruth.at(times)

    def run(extra_rate, horizon=0.6):
        poses = truth @ so3.exp(np.outer(np.cumsum(extra_rate) * 0.002, [1.0, 0.0, 0.0]))
        check = MotionConsistencyCheck(city.camera, 0.3, 0.05, 0.04, 0.9, 2, drift_horizon=horizon)
        return _feed_check(check, city, times, poses, 1.55), check

    failed, check = run(np.zeros_like(times))
    assert failed is None and check.max_drift_deg < 0.75, check.summary()
    steady = np.where(times >= 0.6, 0.2, 0.0)
    failed, check = run(steady, horizon=0.0)  # the ratio rule alone does not see it
    assert failed is None and check.summary()["min_ratio"] > 0.9, check.summary()
    failed, check = run(steady)
    assert failed is not None and "slow drift" in check.failure, check.summary()
    assert 0.55 <= failed <= 0.75, failed
    failed, check = run(np.where((times >= 0.6) & (times < 0.8), 0.2, 0.0))
    assert failed is None, (check.failure, check.summary())
