"""Baselines RTPT, CMax-GAE and IMU dead reckoning: tracking accuracy, RTPT's loss at the map border, bounded
memory of CMax-GAE, the registry and the ``baseline`` command."""
import json

import numpy as np
import pytest

from ti_cmax import cli
from ti_cmax.errors import InputError
from ti_cmax.metrics import evaluate_rotations
from ti_cmax.pipelines.baselines import BASELINES, BaselineConfig, GAEConfig, run_baseline
from ti_cmax.pipelines.baselines.cmax_gae import SphereMap


@pytest.fixture(scope="module")
def slow_sequence(ti_runtime):
    """1.2 s DAVIS240C, slow small-amplitude random motion that stays near the map centre."""
    from ti_cmax.simulate import SimulatorConfig, simulate_sequence

    return simulate_sequence(SimulatorConfig(scene="city", duration=1.2, max_angular_velocity=1.0, seed=1))


@pytest.mark.slow
def test_rtpt_tracks_near_map_centre(slow_sequence):
    seq = slow_sequence
    result = run_baseline("rtpt", seq.events, seq.camera)
    rep = result.report
    assert rep["status"] == "ok" and "lost_at" not in rep
    assert rep["events_processed"] == len(seq.events) and rep["us_per_event"]["frontend"] > 0
    assert rep["parameters"]["rtpt_packet_size"] == 1500 and rep["map_updates"] > 0.9 * rep["packets"]
    err = evaluate_rotations(seq.groundtruth, result.trajectory)
    assert err.abs_rmse_deg < 3.0
    assert result.map.shape == (512, 1024) and 0 <= result.map.min() and result.map.max() <= 1


@pytest.mark.slow
def test_rtpt_loses_track_at_the_map_border(ti_runtime):
    """A constant pan about the vertical axis: tracking is lost when the view reaches lon = +-180 deg."""
    from ti_cmax.simulate import SimulatorConfig, simulate_sequence

    seq = simulate_sequence(SimulatorConfig(scene="bay", sensor="DVS128", duration=1.2, trajectory="constant",
                                            constant_rate_deg=170.0, rotation_axis=(0.0, 1.0, 0.0), seed=1))
    result = run_baseline("rtpt", seq.events, seq.camera)
    rep = result.report
    assert rep["status"] == "lost"
    r_gt = seq.groundtruth.at([rep["lost_at"]])[0]
    assert abs(np.degrees(np.arctan2(r_gt[0, 2], r_gt[2, 2]))) > 150  # near the border, not earlier
    assert result.trajectory.t_end < rep["lost_at"]
    assert evaluate_rotations(seq.groundtruth, result.trajectory).abs_rmse_deg < 3.0  # fine until then


@pytest.mark.slow
def test_cmax_gae_tracks_slow_sequence_with_bounded_memory(slow_sequence):
    seq = slow_sequence
    cfg = BaselineConfig(gae=GAEConfig(gae_sphere_height=512))
    result = run_baseline("cmax-gae", seq.events, seq.camera, cfg)
    rep = result.report
    # 1 of 4 per 25 ms interval, but never fewer than gae_min_sampled_events (15000) per interval
    t = seq.events.t
    edges = np.searchsorted(t, t[0] + 0.025 * np.arange(int(np.ceil((t[-1] - t[0]) / 0.025)) + 1), side="left")
    edges[-1] = len(t)
    n_k = np.diff(edges)
    q_k = np.clip(n_k // 15000, 1, 4)
    assert rep["status"] == "ok" and rep["events_used"] == int(np.sum(-(-n_k // q_k)))
    assert (q_k < 4).any() and (q_k > 1).any()  # both regimes occur in this sequence
    err = evaluate_rotations(seq.groundtruth, result.trajectory)
    assert err.abs_rmse_deg < 5.0
    assert np.allclose(np.diff(result.trajectory.t), 0.025)  # 40 Hz poses
    # the past-event memory has the configured fixed size, whatever the number of intervals
    assert rep["intervals"] > 30 and rep["sphere_bytes"] == 512 * 1024 * 4
    half = run_baseline("cmax-gae", seq.events[: len(seq.events) // 3], seq.camera,
                        BaselineConfig(gae=GAEConfig(gae_sphere_height=512, gae_iterations=2)))
    assert half.report["sphere_bytes"] == rep["sphere_bytes"] and result.map.shape == half.map.shape
    # reproducible bit for bit (no float atomics anywhere in its kernels)
    again = run_baseline("cmax-gae", seq.events[: len(seq.events) // 3], seq.camera,
                         BaselineConfig(gae=GAEConfig(gae_sphere_height=512, gae_iterations=2)))
    np.testing.assert_array_equal(again.trajectory.R, half.trajectory.R)


def test_sphere_map_size_is_fixed(ti_runtime):
    rng = np.random.default_rng(0)
    sphere = SphereMap(64)
    size = sphere.nbytes
    for _ in range(50):  # many intervals
        b = rng.normal(size=(20000, 3)).astype(np.float32)
        sphere.add(b, np.eye(3)[None].repeat(len(b), 0))
    assert sphere.nbytes == size and sphere.hist.shape == (64, 128)
    assert sphere.events == 10**6 and sphere.hist.sum() == pytest.approx(10**6, rel=0.05)


def test_registry_and_unknown_name(slow_sequence):
    assert {"rtpt", "cmax-gae", "imu"} <= set(BASELINES)
    with pytest.raises(InputError, match="unknown baseline 'nope'.*rtpt"):
        run_baseline("nope", slow_sequence.events, slow_sequence.camera)
    with pytest.raises(InputError, match="IMU"):
        run_baseline("imu", slow_sequence.events, slow_sequence.camera)


@pytest.fixture(scope="module")
def tiny_dataset(ti_runtime, tmp_path_factory):
    from ti_cmax.simulate import SimulatorConfig, simulate_sequence, write_sequence

    seq = simulate_sequence(SimulatorConfig(scene="bay", sensor="DVS128", duration=0.6, max_angular_velocity=1.5,
                                            seed=4))
    out = tmp_path_factory.mktemp("bl") / "tiny"
    write_sequence(seq, out)
    return out


@pytest.mark.slow
def test_baseline_command(tiny_dataset, tmp_path, monkeypatch, capsys):
    monkeypatch.setitem(cli.COMMANDS, "baseline", "baseline")  # registered by the lead in cli.py
    out = tmp_path / "rtpt"
    assert cli.main(["baseline", "rtpt", str(tiny_dataset), "--out", str(out), "--quiet", "--refine",
                     "--set", "rtpt_pano_height=256", "--set", "pano_height=256"]) == 0
    for name in ("trajectory.txt", "map.png", "map.npy", "report.json", "config.yaml",
                 "refined/trajectory.txt", "refined/map.png", "refined/report.json"):
        assert (out / name).is_file(), name
    rep = json.loads((out / "report.json").read_text())
    assert rep["status"] == "ok" and rep["method"] == "rtpt" and rep["parameters"]["rtpt_pano_height"] == 256
    assert json.loads((out / "refined" / "report.json").read_text())["method"] == "cmax-ba"
    out = tmp_path / "gae"
    assert cli.main(["baseline", "cmax-gae", str(tiny_dataset), "--out", str(out), "--quiet"]) == 0
    assert np.loadtxt(out / "angular_velocity.txt").shape[1] == 4 and (out / "map.png").is_file()
    out = tmp_path / "imu"
    assert cli.main(["baseline", "imu", str(tiny_dataset), "--out", str(out), "--quiet"]) == 0
    assert json.loads((out / "report.json").read_text())["status"] == "ok"
    assert len(np.loadtxt(out / "trajectory.txt")) > 100
    capsys.readouterr()
    bad = tmp_path / "bad"
    assert cli.main(["baseline", "smt-nope", str(tiny_dataset), "--out", str(bad), "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "unknown baseline 'smt-nope'" in err[0]
    assert not bad.exists()


@pytest.mark.slow
@pytest.mark.parametrize("name", ["rtpt", "cmax-gae", "imu"])
def test_baselines_stream_their_input(slow_sequence, name):
    """Uneven chunks from a generator (never the whole stream at once) give the same result as one Events."""

    seq = slow_sequence
    cfg = BaselineConfig(gae=GAEConfig(gae_sphere_height=256, gae_iterations=3))
    events = seq.events[: len(seq.events) // 2]
    whole = run_baseline(name, events, seq.camera, cfg, imu=seq.imu)
    cuts = np.sort(np.random.default_rng(2).integers(0, len(events), 40))

    def chunks():
        for a, b in zip(np.r_[0, cuts], np.r_[cuts, len(events)]):
            yield events[a:b]

    streamed = run_baseline(name, chunks(), seq.camera, cfg, imu=seq.imu)
    np.testing.assert_array_equal(streamed.trajectory.t, whole.trajectory.t)
    np.testing.assert_array_equal(streamed.trajectory.R, whole.trajectory.R)
    np.testing.assert_array_equal(streamed.map, whole.map)
    assert streamed.report["events_processed"] == whole.report["events_processed"] == len(events)


@pytest.mark.parametrize("n,minimum,expected", [(80000, 15000, 4), (40000, 15000, 2), (17500, 15000, 1),
                                                (100, 15000, 1), (17500, 0, 4)])
def test_cmax_gae_sampling_keeps_enough_events(n, minimum, expected):
    """1 of Q (the original's 4) at high event rates, fewer skipped at low rates; 0 restores the fixed 1 of Q."""
    from ti_cmax.pipelines.baselines.cmax_gae import sample_step

    assert sample_step(n, GAEConfig(gae_min_sampled_events=minimum)) == expected
