"""Rotational event simulator: scenes, trajectories, events, IMU, output folder, command line."""
import json

import numpy as np
import pytest

from ti_cmax import so3
from ti_cmax.errors import InputError
from ti_cmax.simulate import SimulatorConfig, make_motion, simulate_sequence, simulate_to_folder
from ti_cmax.simulate import scenes
from ti_cmax.simulate.generate import pixel_speed_factor, render_times, sensor_camera

SHORT = dict(sensor="DVS128", duration=0.3, max_angular_velocity=2.0, seed=3)


@pytest.fixture(scope="module")
def seq():
    return simulate_sequence(SimulatorConfig(**SHORT))


def panoramic_iwe(events, camera, rotations, w=1024, h=512):
    """Bilinear voting of rotated bearings into an equirectangular image (CONVENTIONS.md), numpy."""
    d = np.einsum("nij,nj->ni", rotations, camera.bearings(events.x, events.y, dtype=np.float64))
    lon = np.arctan2(d[:, 0], d[:, 2])
    lat = np.arcsin(d[:, 1] / np.linalg.norm(d, axis=1))
    u = w / 2 + w * lon / (2 * np.pi)
    v = h / 2 + h * lat / np.pi
    u0, v0 = np.floor(u).astype(int), np.floor(v).astype(int)
    fu, fv = u - u0, v - v0
    img = np.zeros((h, w))
    for du, dv, wt in ((0, 0, (1 - fu) * (1 - fv)), (1, 0, fu * (1 - fv)), (0, 1, (1 - fu) * fv), (1, 1, fu * fv)):
        np.add.at(img, (np.clip(v0 + dv, 0, h - 1), (u0 + du) % w), wt)
    return img


# events ------------------------------------------------------------------------------------------
@pytest.mark.slow
def test_short_dvs128_run_is_valid(seq):
    ev = seq.events
    cam = seq.camera
    assert (cam.width, cam.height) == (128, 128)
    ev.validate(cam.width, cam.height)  # sorted, finite, on the sensor
    assert len(ev) > 20_000
    assert 0.0 <= ev.t[0] and ev.t[-1] <= SHORT["duration"] + 1e-6
    assert set(np.unique(ev.p)) == {-1, 1}
    # timestamps are on the 1 us grid
    np.testing.assert_allclose(ev.t * 1e6, np.round(ev.t * 1e6), atol=1e-3)
    # events appear where the texture moves: most pixels fire
    assert len(np.unique(ev.y.astype(int) * cam.width + ev.x)) > 0.7 * cam.width * cam.height
    np.testing.assert_allclose(seq.groundtruth.R[0], np.eye(3), atol=1e-12)
    assert seq.info["num_events"] == len(ev)


def test_groundtruth_warp_is_sharper_than_perturbed(seq):
    """Panoramic IWE with the true rotations has clearly higher variance than with 0.5 deg errors."""
    ev = seq.events
    r_gt = seq.groundtruth.at(ev.t)
    a = np.array([0.6, -0.3, 0.74])
    a /= np.linalg.norm(a)
    b = np.cross(a, [0.0, 0.0, 1.0])
    b /= np.linalg.norm(b)
    c = np.cross(a, b)
    phase = 2 * np.pi * ev.t / 0.1
    pert = so3.exp(np.radians(0.5) * (np.cos(phase)[:, None] * b + np.sin(phase)[:, None] * c))
    var_gt = panoramic_iwe(ev, seq.camera, r_gt).var()
    var_pert = panoramic_iwe(ev, seq.camera, r_gt @ pert).var()
    assert var_gt > 1.3 * var_pert


def test_event_count_scales_inversely_with_threshold():
    base = dict(SHORT, duration=0.2, threshold_sigma=0.0)
    n_lo = len(simulate_sequence(SimulatorConfig(**base, contrast_threshold=0.15)).events)
    n_hi = len(simulate_sequence(SimulatorConfig(**base, contrast_threshold=0.3)).events)
    # ~1/C; a little above 2 because low-contrast texture (log steps between the two thresholds)
    # only triggers the lower threshold
    assert 1.9 < n_lo / n_hi < 2.8


@pytest.mark.slow
def test_noise_events_and_refractory_period():
    base = dict(SHORT, duration=0.2, max_angular_velocity=0.0, trajectory="random")
    quiet = simulate_sequence(SimulatorConfig(**base))
    assert len(quiet.events) == 0  # no motion, no noise: no events
    noisy = simulate_sequence(SimulatorConfig(**base, noise_rate=5.0))
    expected = 5.0 * 128 * 128 * 0.2
    assert abs(len(noisy.events) - expected) < 5 * np.sqrt(expected)
    refr = simulate_sequence(SimulatorConfig(**dict(SHORT, duration=0.2), refractory_period=5e-3)).events
    pix = refr.y.astype(np.int64) * 128 + refr.x
    order = np.lexsort((refr.t, pix))
    same = np.diff(pix[order]) == 0
    assert np.all(np.diff(refr.t[order])[same] >= 5e-3 - 1.5e-6)  # timestamps rounded to 1 us


def test_hot_pixels_fire_at_their_rate_on_a_still_camera():
    base = dict(SHORT, duration=0.5, max_angular_velocity=0.0, trajectory="random")
    ev = simulate_sequence(SimulatorConfig(**base, hot_pixels=3, hot_pixel_rate=400.0)).events
    pixels, counts = np.unique(ev.y.astype(np.int64) * 128 + ev.x, return_counts=True)
    assert len(pixels) == 3  # only the hot pixels fire
    assert np.all(np.abs(counts - 200) < 5 * np.sqrt(200))  # 400 Hz x 0.5 s each, Poisson
    assert set(np.unique(ev.p)) == {-1, 1}
    again = simulate_sequence(SimulatorConfig(**base, hot_pixels=3, hot_pixel_rate=400.0)).events
    np.testing.assert_array_equal(again.x, ev.x)  # seeded


# IMU and ground truth ----------------------------------------------------------------------------
def test_imu_gyro_matches_groundtruth_within_noise(seq):
    cfg = seq.config
    imu = seq.imu
    assert len(imu) == int(round(cfg.duration * cfg.imu_rate)) + 1
    resid = imu.gyro - seq.gyro_bias - seq.motion.omega(imu.t)
    assert np.all(np.abs(resid.mean(axis=0)) < 5 * cfg.gyro_noise_std / np.sqrt(len(imu)))
    np.testing.assert_allclose(resid.std(axis=0), cfg.gyro_noise_std, rtol=0.2)
    assert 0 < np.abs(seq.gyro_bias).max() < 5 * cfg.gyro_bias_std
    # accelerometer: gravity rotated into the camera frame, |acc| ~ g
    np.testing.assert_allclose(np.linalg.norm(imu.acc, axis=1).mean(), cfg.gravity, rtol=1e-2)
    np.testing.assert_allclose(imu.acc[0], [0, -cfg.gravity, 0], atol=5 * cfg.acc_noise_std)


def test_integrated_groundtruth_is_exact_enough():
    fine = make_motion("random", 1.0, seed=5, max_angular_velocity=6.0, integration_rate=10000.0)
    finer = make_motion("random", 1.0, seed=5, max_angular_velocity=6.0, integration_rate=40000.0)
    t = np.linspace(0, 1.0, 333)
    err = so3.geodesic_angle(fine.rotation(t), finer.rotation(t))
    assert np.degrees(err.max()) < 1e-4
    # omega is the body-frame derivative: R(t)^T dR/dt = [omega]x
    h = 1e-5
    dr = (fine.rotation(t[1:-1] + h) - fine.rotation(t[1:-1] - h)) / (2 * h)
    om = so3.vee(np.swapaxes(fine.rotation(t[1:-1]), 1, 2) @ dr)
    np.testing.assert_allclose(om, fine.omega(t[1:-1]), atol=1e-4)
    # the ramp: slow start, peak near the requested value
    speed = np.linalg.norm(fine.omega(np.linspace(0, 1, 2001)), axis=1)
    assert speed[:200].max() < 0.5 * speed.max() and speed.max() == pytest.approx(6.0, rel=1e-2)


def test_pan_and_constant_trajectories():
    pan = make_motion("pan", 2.0)
    r = pan.rotation([0.0, 1.0, 2.0])
    np.testing.assert_allclose(r[1], so3.exp([0, np.pi, 0]), atol=1e-8)  # half way: facing backwards
    np.testing.assert_allclose(r[2], np.eye(3), atol=1e-8)  # full turn
    const = make_motion("constant", 3.0, constant_rate_deg=4.0, axis=(0, 0, 1))
    np.testing.assert_allclose(const.rotation([3.0])[0], so3.exp([0, 0, np.radians(12.0)]), atol=1e-10)
    rnd_axis = make_motion("constant", 1.0, seed=2)
    assert np.linalg.norm(rnd_axis.omega(0.5)) == pytest.approx(np.radians(4.0))


def test_multi_turn_pan_with_wobble():
    """--trajectory pan --turns N: N full turns about the world vertical (loop closure benchmarks); the wobble is a
    seeded bounded tilt that vanishes with its rate at both ends, so the pan ends N turns round and however many
    turns it makes its axis stays the world vertical."""
    pan = make_motion("pan", 4.0, turns=2.5)
    np.testing.assert_allclose(pan.rotation([4.0])[0], so3.exp([0, np.pi, 0]), atol=1e-7)  # 2.5 turns
    assert np.linalg.norm(pan.omega(2.0)) == pytest.approx(2 * 2 * np.pi * 2.5 / 4.0)  # peak rate mid-way
    wob = make_motion("pan", 20.0, turns=4.0, wobble=1.0, seed=5)
    t = np.linspace(0, 20, 2001)
    rot = wob.rotation(t)
    np.testing.assert_allclose(rot[-1], np.eye(3), atol=1e-6)  # four turns, tilt gone
    np.testing.assert_allclose(wob.omega([0.0, 20.0]), np.zeros((2, 3)), atol=1e-12)
    theta = 2 * np.pi * 4.0 / 20.0 * (t - 20.0 / (2 * np.pi) * np.sin(2 * np.pi * t / 20.0))
    tilt = so3.geodesic_angle(so3.exp(theta[:, None] * np.array([0.0, 1.0, 0.0])), rot)
    assert np.radians(3) < tilt.max() < np.radians(30)  # a wobble, bounded over the four turns
    # the body rate is the integrated rotation's: finite differences of R agree with omega
    h = 1e-4
    for tq in (3.1, 11.7):
        r0, r1 = wob.rotation([tq - h, tq + h])
        np.testing.assert_allclose(so3.log(r0.T @ r1) / (2 * h), wob.omega([tq])[0], atol=2e-4)
    np.testing.assert_array_equal(wob.omega([1.3]), make_motion("pan", 20.0, turns=4.0, wobble=1.0, seed=5).omega([1.3]))


def test_render_times_bound_pixel_motion():
    cam = sensor_camera("DAVIS240C")
    motion = make_motion("random", 1.0, seed=1, max_angular_velocity=5.0)
    times = render_times(motion, cam, max_pixel_step=0.2, max_dt=2e-3)
    assert times[0] == 0 and times[-1] == 1.0 and np.all(np.diff(times) > 0) and np.diff(times).max() <= 2e-3 + 1e-12
    # largest pixel displacement between consecutive renders, measured on a pixel grid
    b = cam.bearing_lut[::97].astype(float)
    r = motion.rotation(times)
    k = np.argsort(np.diff(times))[:50]  # the fastest steps
    moved = [np.abs(cam.project((r[i + 1].T @ r[i] @ b.T).T) - cam.project(b)).max() for i in k]
    assert max(moved) <= 0.2
    assert pixel_speed_factor(cam) > cam.fx


# scenes ------------------------------------------------------------------------------------------
@pytest.mark.parametrize("name", ["bicycle", "city", "street", "town", "bay"])
def test_procedural_scenes_have_edges_at_all_latitudes(name):
    img = scenes.procedural_scene(name, 128, seed=0)
    assert img.shape == (128, 256) and img.dtype == np.float32
    assert img.min() >= 0.05 and img.max() <= 1.0
    edges = np.abs(np.diff(img, axis=1)).max(axis=1) + np.abs(np.diff(img, axis=0, append=img[-1:])).max(axis=1)
    bands = edges[4:-4].reshape(8, -1).max(axis=1)  # 8 latitude bands (rows near the poles excluded)
    assert np.all(bands > 0.05)
    np.testing.assert_array_equal(img, scenes.procedural_scene(name, 128, seed=0))
    assert not np.array_equal(img, scenes.procedural_scene(name, 128, seed=1))


def test_star_field_and_antialiasing():
    stars = scenes.star_field(256, 200, pixel_angle=1 / 110, seed=0)
    assert stars.min() == 0.0 and 0.15 <= stars.max() <= 1.0
    assert (stars > 0.01).mean() < 0.05  # sparse
    blurred = scenes.antialias(stars, 0.5 / 110)
    assert blurred.max() < stars.max() and blurred.sum() == pytest.approx(stars.sum(), rel=0.02)
    assert np.all(np.isfinite(scenes.log_panorama(blurred, 0.01)))


def test_image_scene_and_bad_image(tmp_path):
    import imageio.v3 as iio

    yy, xx = np.mgrid[0:50, 0:100]
    img = np.round(127 + 100 * np.sin(2 * np.pi * xx / 100) * np.cos(np.pi * yy / 50)).astype(np.uint8)
    path = tmp_path / "pano.png"
    iio.imwrite(path, np.dstack([img] * 3))
    pano = scenes.make_panorama(SimulatorConfig(image=str(path), pano_height=100, blur_sigma_px=0.0), 0.01)
    assert pano.shape == (100, 200)
    np.testing.assert_allclose(pano[::2, ::2], img / 255.0, atol=0.02)
    bad = tmp_path / "bad.png"
    bad.write_bytes(b"not an image")
    with pytest.raises(InputError, match="bad.png"):
        scenes.make_panorama(SimulatorConfig(image=str(bad)), 0.01)


def test_config_validation_and_loading(tmp_path):
    from ti_cmax.config import load_config

    with pytest.raises(InputError, match="sensor"):
        SimulatorConfig(sensor="DAVIS9000")
    with pytest.raises(InputError, match="contrast_threshold"):
        SimulatorConfig(contrast_threshold=-0.1)
    cfg_file = tmp_path / "sim.yaml"
    cfg_file.write_text("scene: bay\nduration: 1.5\nrotation_axis: [0, 1, 0]\n")
    cfg = load_config(SimulatorConfig, cfg_file, ["contrast_threshold=0.25", "sensor=VGA"])
    assert (cfg.scene, cfg.duration, cfg.contrast_threshold, cfg.sensor) == ("bay", 1.5, 0.25, "VGA")
    assert cfg.rotation_axis == (0, 1, 0)


def test_sensors():
    for name, size in (("DAVIS240C", (240, 180)), ("DVS128", (128, 128)), ("DAVIS346", (346, 260)),
                       ("VGA", (640, 480)), ("DVXplorer", (640, 480)), ("HD", (1280, 720))):
        cam = sensor_camera(name)
        assert cam.size == size
    davis = sensor_camera("DAVIS240C")
    assert davis.has_distortion and davis.dist[0] == pytest.approx(-0.368)
    vga, dvx, hd = sensor_camera("VGA"), sensor_camera("DVXplorer"), sensor_camera("HD")
    assert vga.fx == 440.0 and not vga.has_distortion  # unchanged for existing configs
    assert (dvx.fx, dvx.fy, dvx.cx, dvx.cy) == (520.0, 520.0, 319.5, 239.5) and not dvx.has_distortion
    # IMX636: 4.86 um pixels behind a 6 mm lens, 55 x 33 deg, mild barrel distortion
    assert hd.fx == hd.fy == pytest.approx(6e-3 / 4.86e-6, rel=1e-3) and hd.dist[0] < 0
    assert 2 * np.degrees(np.arctan(640 / hd.fx)) == pytest.approx(54.8, abs=0.1)
    # per-sensor contrast threshold (their usual event rates), resolved once; a value the user gives wins
    resolved = {s: SimulatorConfig(sensor=s).resolved().contrast_threshold for s in ("DAVIS240C", "DVXplorer", "HD")}
    assert resolved == {"DAVIS240C": 0.2, "DVXplorer": 0.25, "HD": 0.35}
    assert SimulatorConfig(sensor="HD", contrast_threshold=0.3).resolved().contrast_threshold == 0.3


@pytest.mark.slow
def test_hd_simulation_streams_in_bounded_chunks(tmp_path, monkeypatch):
    """A short HD simulation renders in chunks whose buffer stays under chunk_megabytes and writes each chunk
    as it comes (so 1 s of HD streams to disk in bounded memory)."""
    from ti_cmax.io import EventsH5Writer, open_dataset
    from ti_cmax.kernels import render as rk

    buffers, appended = [], []
    real_render, real_append = rk.render_and_count, EventsH5Writer.append

    def render_and_count(*args, **kw):
        lbuf, counts = real_render(*args, **kw)
        buffers.append(lbuf.nbytes)
        return lbuf, counts

    def append(self, events):
        appended.append(len(events))
        return real_append(self, events)

    monkeypatch.setattr(rk, "render_and_count", render_and_count)
    monkeypatch.setattr(EventsH5Writer, "append", append)
    cfg = SimulatorConfig(sensor="HD", duration=0.02, trajectory="constant", constant_rate_deg=12.0,
                          rotation_axis=(0.3, 1.0, 0.1), pano_height=1024, chunk_megabytes=32.0)
    info = simulate_to_folder(cfg, tmp_path / "hd", show_progress=False)
    assert len(buffers) >= 3 and max(buffers) <= 32 * 2**20
    assert len(appended) == len(buffers) and sum(appended) == info["num_events"] > 10_000
    assert info["config"]["contrast_threshold"] == 0.35 and info["camera"]["width"] == 1280
    ds = open_dataset(tmp_path / "hd")
    assert ds.sensor_size == (1280, 720) and ds.camera.fx == sensor_camera("HD").fx


# output folder and command line ------------------------------------------------------------------
def test_output_folder_contents(tmp_path):
    from ti_cmax.io import open_dataset, read_angular_velocity, read_calib, read_imu_txt, read_tum

    out = tmp_path / "sim"
    info = simulate_to_folder(SimulatorConfig(**dict(SHORT, duration=0.2)), out, show_progress=False)
    names = {"events.txt", "events.h5", "calib.txt", "groundtruth.txt", "imu.txt",
             "groundtruth_angular_velocity.txt", "panorama.png", "simulation.json"}
    assert names <= {p.name for p in out.iterdir()}
    js = json.loads((out / "simulation.json").read_text())
    assert js["num_events"] == info["num_events"] > 1000
    assert js["seed"] == 3 and len(js["gyro_bias"]) == 3 and js["config"]["sensor"] == "DVS128"
    cam = read_calib(out / "calib.txt", 128, 128)
    assert cam.fx == pytest.approx(sensor_camera("DVS128").fx)
    gt = read_tum(out / "groundtruth.txt")
    assert gt.t[-1] == pytest.approx(0.2) and len(gt) == 201
    imu = read_imu_txt(out / "imu.txt")
    np.testing.assert_allclose(imu.gyro.mean(axis=0), 0, atol=1.0)
    t_w, w = read_angular_velocity(out / "groundtruth_angular_velocity.txt")
    assert len(t_w) == 201 and w.shape == (201, 3)
    # the in-memory API produces the same events as the streamed folder
    mem = simulate_sequence(SimulatorConfig(**dict(SHORT, duration=0.2)))
    assert len(mem.events) == js["num_events"]
    for fname in ("events.txt", "events.h5"):
        ds = open_dataset(out / fname)
        assert (ds.width, ds.height) == (128, 128)
        ev = ds.read_events()
        assert len(ev) == js["num_events"]
        np.testing.assert_allclose(ev.t, mem.events.t, atol=1e-9)
        np.testing.assert_array_equal(ev.x, mem.events.x)
        np.testing.assert_array_equal(ev.p, mem.events.p)


def test_failed_run_leaves_nothing(tmp_path, monkeypatch):
    import ti_cmax.simulate.sequence as sequence

    real = sequence.generate_events

    def broken(*args, **kw):
        for chunk in real(*args, **kw):
            yield chunk
            raise RuntimeError("disk full")

    monkeypatch.setattr(sequence, "generate_events", broken)
    out = tmp_path / "sim"
    with pytest.raises(RuntimeError, match="disk full"):
        simulate_to_folder(SimulatorConfig(**dict(SHORT, duration=0.2, chunk_megabytes=1.0)), out,
                           show_progress=False)
    assert not out.exists()


def test_cli(tmp_path, capsys):
    from ti_cmax.cli import main

    out = tmp_path / "cli"
    rc = main(["simulate", str(out), "--sensor", "DVS128", "--duration", "0.1", "--scene", "bay",
               "--contrast-threshold", "0.3", "--seed", "4", "--quiet", "--set", "gyro_noise_std=0.001"])
    assert rc == 0
    js = json.loads((out / "simulation.json").read_text())
    assert js["config"]["scene"] == "bay" and js["config"]["contrast_threshold"] == 0.3
    assert js["config"]["gyro_noise_std"] == 0.001 and js["seed"] == 4
    bad = tmp_path / "bad"
    rc = main(["simulate", str(bad), "--image", str(tmp_path / "missing.png"), "--quiet"])
    assert rc == 2 and not bad.exists()
    assert "missing.png" in capsys.readouterr().err


def test_cli_events_format(tmp_path):
    """--format h5 (default) / txt / both: only the chosen events files, the same events in each."""
    from ti_cmax.cli import main
    from ti_cmax.io import open_dataset

    args = ["--sensor", "DVS128", "--duration", "0.05", "--scene", "bay", "--quiet"]
    files = {}
    for fmt in (None, "txt", "both"):
        out = tmp_path / f"f_{fmt}"
        assert main(["simulate", str(out), *args, *(["--format", fmt] if fmt else [])]) == 0
        files[fmt] = {p.name for p in out.glob("events.*")}
    assert files == {None: {"events.h5"}, "txt": {"events.txt"}, "both": {"events.h5", "events.txt"}}
    n = json.loads((tmp_path / "f_None" / "simulation.json").read_text())["num_events"]
    assert len(open_dataset(tmp_path / "f_txt").read_events()) == len(open_dataset(tmp_path / "f_None").read_events()) == n


def test_star_scene_defaults_to_a_slow_constant_rotation():
    """The stars scene with the random ECD-like motion (5 rad/s peak) is nothing a star tracker sees: by default it
    now turns at a constant 4 deg/s; an explicit trajectory still wins, and other scenes keep the random motion."""

    assert SimulatorConfig(scene="stars").resolved().trajectory == "constant"
    assert SimulatorConfig(scene="stars", trajectory="random").resolved().trajectory == "random"
    assert SimulatorConfig(scene="city").resolved().trajectory == "random"
    assert SimulatorConfig(scene="stars", image="pano.png").motion_kind == "random"
    seq = simulate_sequence(SimulatorConfig(scene="stars", num_stars=300, duration=0.2, seed=1))
    assert seq.info["trajectory"]["kind"] == "constant"
    assert seq.info["trajectory"]["peak_angular_velocity"] == pytest.approx(np.radians(4.0))
