"""Defaults derived from the sensor (pipelines/sensor_defaults.py): the documented rule per preset, user values
win and are written back as numbers, and a VGA / HD packet recovers a known omega with the derived packet size."""
import numpy as np
import pytest
import yaml

from ti_cmax import Camera, Events, so3
from ti_cmax.config import SlamConfig, load_config
from ti_cmax.pipelines.frontend import AngularVelocityEstimator
from ti_cmax.pipelines.sensor_defaults import derived_summary, resolve_config

DAVIS240C = Camera(240, 180, 199.1, 198.9, 132.2, 110.7)
DVS128 = Camera(128, 128, 110.0, 110.0, 63.5, 63.5)
VGA = Camera(640, 480, 520.0, 520.0, 319.5, 239.5)
HD = Camera(1280, 720, 1235.0, 1235.0, 639.5, 359.5)


@pytest.mark.parametrize("sensor, d, packet, cap, rate, map_w, window_cap, d_ba", [
    ("DVS128", 1, 10000, 20000, 3792.6, 1280, 82000, 1),   # smaller sensor: packets stay at the reference's size
    ("DAVIS240C", 1, 10000, 20000, 10000.0, 2048, 216000, 1),
    ("DAVIS346", 1, 21000, 42000, 20824.1, 2560, 450000, 1),  # at d = 2 its IWE would have fewer pixels than 43 200
    ("DVXplorer", 2, 18000, 53000, 71111.1, 5120, 419000, 2),  # IWE 320 x 240; cap 3N; BA map 2560 x 1280
    ("HD", 2, 53000, 160000, 213333.3, 8192, 571000, 2),  # IWE 640 x 360; map width at its cap; BA map 4096 wide
])
def test_derived_values_follow_the_documented_rules(sensor, d, packet, cap, rate, map_w, window_cap, d_ba):
    from ti_cmax.simulate import sensor_camera

    camera = sensor_camera(sensor)
    cfg = resolve_config(SlamConfig(), camera)
    f, b = cfg.frontend, cfg.backend
    assert (f.frontend_iwe_downsample, f.num_events_per_packet, f.frontend_max_packet_events) == (d, packet, cap)
    assert f.frontend_min_event_rate == pytest.approx(rate, abs=0.1) and b.backend_min_ev_rate == f.frontend_min_event_rate
    assert b.pano_size == (map_w, map_w // 2)
    # about 1.5 map pixels per sensor pixel at the image centre (at most 8192 wide), never coarser than the sensor
    ratio = map_w / (2 * np.pi * 0.5 * (camera.fx + camera.fy))
    assert 1.5 <= ratio < 1.5 + 256 / (2 * np.pi * camera.fx) or (map_w == 8192 and ratio >= 1.0)
    assert b.backend_max_window_events == window_cap
    assert b.backend_map_downsample == d_ba
    # the sensor's view on the BA map: at least a DAVIS240C's at the default scale, or d = 1
    assert d_ba == 1 or camera.width * camera.height * (ratio / d_ba) ** 2 >= 43200 * 1.5**2
    assert cfg.realtime.realtime_min_window_events == round(window_cap / 5, -3)  # a fifth of the cap
    assert resolve_config(cfg, camera) == cfg  # idempotent: resolved values are plain numbers


def test_user_values_win_and_are_written_back(tmp_path):
    from ti_cmax.config import save_config

    cfg = load_config(SlamConfig, None, ["num_events_per_packet=30000", "pano_height=auto"])
    assert cfg.backend.pano_height == 0
    resolved = resolve_config(cfg, VGA)
    assert resolved.frontend.num_events_per_packet == 30000 and resolved.backend.pano_height == 2560
    assert "num_events_per_packet" not in derived_summary(cfg, VGA) and derived_summary(cfg, VGA)["pano_height"] == 2560
    save_config(resolved, tmp_path / "config.yaml")
    text = yaml.safe_load((tmp_path / "config.yaml").read_text())
    assert text["backend"]["pano_height"] == 2560 and text["frontend"]["frontend_max_packet_events"] == 53000
    assert text["frontend"]["frontend_iwe_downsample"] == 2
    assert load_config(SlamConfig, tmp_path / "config.yaml") == resolved  # a rerun with that file is exact


@pytest.mark.parametrize("camera, sigma, d", [
    (VGA, 1.0, 2), (HD, 1.0, 2), (DAVIS240C, 1.0, 1), (DVS128, 1.0, 1),
    (VGA, 2.0, 2),  # d <= 4 by the blur, but 3 and 4 leave the IWE under 43 200 pixels
    (HD, 2.0, 4),  # 320 x 180
    (HD, 0.3, 1),  # a narrow blur: an IWE pixel of 2 x 2 would spread the votes more than the blur
])
def test_iwe_downsampling_follows_the_blur_and_the_pixel_count(camera, sigma, d):
    from ti_cmax.config import FrontendConfig
    from ti_cmax.pipelines.sensor_defaults import iwe_downsample_for

    assert iwe_downsample_for(camera, sigma) == d
    cfg = resolve_config(SlamConfig(frontend=FrontendConfig(frontend_blur_sigma=sigma)), camera).frontend
    assert cfg.frontend_iwe_downsample == d
    est = AngularVelocityEstimator(camera, cfg)
    # the IWE covers the sensor with d x d pixels, and its blur keeps its width in sensor pixels
    assert (est.iwe_width, est.iwe_height) == (-(-camera.width // d), -(-camera.height // d))
    assert est.ws.blur_sigma == pytest.approx(sigma / d)


@pytest.mark.parametrize("camera, sigma, height, d", [
    (VGA, 1.0, 0, 2), (HD, 1.0, 0, 2), (DAVIS240C, 1.0, 0, 1), (DVS128, 1.0, 0, 1),
    (HD, 0.3, 0, 1),  # a narrow blur: a BA pixel of 2 x 2 map pixels would spread the votes more than the blur
    (HD, 2.0, 0, 2),  # d <= 4 by the blur; at 4 the view holds 64 000 pixels (under 97 200), 3 does not divide 8192
    (VGA, 1.0, 1001, 1),  # a user's map size that 2 does not divide
    (VGA, 1.0, 1024, 1),  # a coarse user map: the view holds 121 000 pixels at d = 1, 30 000 at d = 2
])
def test_ba_map_downsampling_follows_the_blur_and_the_view(camera, sigma, height, d):
    from ti_cmax.config import BackendConfig
    from ti_cmax.pipelines.sensor_defaults import ba_downsample_for, derived_backend

    cfg = BackendConfig(backend_blur_sigma=sigma, pano_height=height)
    b = derived_backend(camera, cfg)
    w, h = 2 * b["pano_height"], b["pano_height"]
    assert ba_downsample_for(camera, w, h, sigma) == b["backend_map_downsample"] == d
    # the window's cap: 5 events per sensor pixel on the full-resolution map; on a coarser one 5 / 1.5^2 per BA-map
    # pixel of the sensor's view, never more than 5 per sensor pixel
    pixels = camera.width * camera.height
    view = pixels * (w / (2 * np.pi * camera.fx) / d) ** 2
    want = 5 * pixels if d == 1 else min(5 * pixels, 5 / 1.5**2 * view)
    assert b["backend_max_window_events"] == pytest.approx(want, abs=500)


def test_iwe_intrinsics_map_sensor_pixels_onto_blocks_of_the_iwe():
    """Sensor pixel i spans [i - 1/2, i + 1/2]; IWE pixel j of factor d covers sensor pixels d j .. d j + d - 1."""
    from ti_cmax.pipelines.frontend import iwe_intrinsics

    d = 3
    Kd = iwe_intrinsics(HD.K, d)
    u = np.array([0.0, 1.0, 2.0, 3.0, 1279.0, -0.5, 1279.5])
    v = np.array([0.0, 2.0, 5.0, 8.0, 719.0, -0.5, 719.5])
    b = HD.unproject(u, v)
    p = (Kd @ b.T).T
    np.testing.assert_allclose(p[:, 0], (u + 0.5) / d - 0.5, atol=1e-9)
    np.testing.assert_allclose(p[:, 1], (v + 0.5) / d - 0.5, atol=1e-9)
    assert np.array_equal(iwe_intrinsics(HD.K, 1), HD.K)


def test_a_ba_map_factor_that_does_not_divide_the_map_is_a_clear_error():
    from ti_cmax.errors import InputError

    cfg = load_config(SlamConfig, None, ["backend_map_downsample=3"])  # the derived 5120 x 2560 map
    with pytest.raises(InputError, match="backend_map_downsample=3 must divide"):
        resolve_config(cfg, VGA)
    assert resolve_config(load_config(SlamConfig, None, ["backend_map_downsample=4"]), VGA).backend.pano_size == \
        (5120, 2560)


def test_unresolved_map_size_is_a_clear_error():
    with pytest.raises(ValueError, match="resolve"):
        SlamConfig().backend.pano_size


def _packet(camera, omega, n, seed):
    """n events of random scene edges seen by a camera rotating at omega during 10 ms around t = 0.005."""
    rng = np.random.default_rng(seed)
    hx, hy = camera.width / (2 * camera.fx), camera.height / (2 * camera.fy)
    centres = np.column_stack([rng.uniform(-hx, hx, 3000), rng.uniform(-hy, hy, 3000), np.ones(3000)])
    dirs = rng.normal(size=(3000, 3)) * [1, 1, 0]
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    s = np.linspace(-0.01, 0.01, 10)
    pts = (centres[:, None] + s[None, :, None] * dirs[:, None]).reshape(-1, 3)
    t = np.sort(rng.uniform(0.0, 0.01, 2 * n))
    x = pts[rng.integers(0, len(pts), len(t))]
    cam_dirs = np.einsum("kji,kj->ki", so3.exp(np.asarray(omega)[None] * (t - 0.005)[:, None]), x)
    pix = camera.project(cam_dirs)
    ok = (pix[:, 0] >= 0) & (pix[:, 0] <= camera.width - 1) & (pix[:, 1] >= 0) & (pix[:, 1] <= camera.height - 1)
    idx = np.sort(rng.choice(np.flatnonzero(ok), n, replace=False))
    return Events(t[idx], pix[idx, 0].astype(np.float32), pix[idx, 1].astype(np.float32), np.ones(n))


@pytest.mark.slow
@pytest.mark.parametrize("camera", [VGA, HD], ids=["VGA", "HD"])
def test_large_sensor_packet_recovers_omega_with_derived_size(ti_runtime, camera):
    omega = np.array([0.9, -1.3, 0.5])
    est = AngularVelocityEstimator(camera, SlamConfig().frontend)
    n = est.config.num_events_per_packet
    e = est.estimate(_packet(camera, omega, n, seed=5), 0.005)
    assert np.linalg.norm(e.omega - omega) < 0.02 * np.linalg.norm(omega), e
    # the motion blurs the packet by ~2 IWE pixels at omega = 0 (10 ms at VGA, d = 2): the contrast gains 40 %
    assert not e.suspect and e.gain > 1.3, e.gain


@pytest.mark.slow
def test_noise_packet_far_from_the_warm_start_is_suspect(ti_runtime):
    """A packet whose IWE does not constrain omega (uniform noise, as an HD IWE of far too few events looks): the
    solution stays pixels away from omega = 0 without sharpening anything, and is flagged; its run is
    "suspect"."""
    from ti_cmax.pipelines.frontend import FrontendRunner, Packet

    rng = np.random.default_rng(3)
    n = 20000
    noise = Events(np.sort(rng.uniform(0, 0.01, n)), rng.integers(0, HD.width, n).astype(np.uint16),
                   rng.integers(0, HD.height, n).astype(np.uint16), np.ones(n))
    runner = FrontendRunner(HD, SlamConfig().frontend)
    every = runner.config.frontend_gain_check_every
    for k in range(2 * every):
        runner.estimator.omega = np.array([1.5, -1.0, 0.5])  # the motion of the packets before
        runner.process(Packet(0.005 + 0.01 * k, noise, 0.01, False))
    res = runner.result()
    checked = np.arange(2 * every) % every == 0  # 1 of frontend_gain_check_every packets is checked
    assert res.suspect[checked].all() and np.all(res.gain[checked] < 1.02) and res.status == "suspect"
    assert not res.suspect[~checked].any() and np.isnan(res.gain[~checked]).all()
    assert res.summary()["suspect_packets"] == res.summary()["checked_packets"] == 2


@pytest.mark.slow
def test_fast_start_is_as_good_as_the_rest(ti_runtime):
    """Fast motion from the first 5 % on (random_ramp_start=1: the map is empty while the camera already turns at
    up to 2 rad/s): the first windows fix the offset of the whole trajectory, so the error in the first 0.3 s must
    be no worse than in the rest, and the whole run accurate."""
    from ti_cmax.metrics import evaluate_rotations
    from ti_cmax.pipelines.slam import run_slam
    from ti_cmax.simulate import SimulatorConfig, simulate_sequence

    seq = simulate_sequence(SimulatorConfig(scene="city", duration=1.0, max_angular_velocity=2.0,
                                            random_ramp_start=1.0, random_frequency_max=3.0, seed=6))
    res = run_slam(seq.events, seq.camera, SlamConfig())
    err = evaluate_rotations(seq.groundtruth, res.trajectory)
    t = err.abs_times
    early, rest = err.abs_errors_deg[t < t[0] + 0.3], err.abs_errors_deg[t >= t[0] + 0.3]
    assert err.abs_rmse_deg < 0.3 and early.max() < max(0.3, 2.0 * rest.max()), (early.max(), rest.max())


def test_loop_min_travel_is_a_turn_less_two_fields_of_view():
    from ti_cmax.config import LoopClosureConfig

    for fov in (50.0, 60.0, 90.0):
        cam = Camera.ideal(320, 240, fov)
        assert resolve_config(SlamConfig(), cam).loop.loop_min_travel == 360.0 - 2 * fov
    user = SlamConfig(loop=LoopClosureConfig(loop_min_travel=-1.0))  # -1: the age rule alone, kept
    assert resolve_config(user, Camera.ideal(320, 240, 60.0)).loop.loop_min_travel == -1.0
