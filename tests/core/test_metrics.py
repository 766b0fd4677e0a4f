"""Metrics of Sec. IV-B on hand-made trajectories with known errors, EA/GM by hand, evo agreement, CLI."""
import json
import re

import numpy as np
import pytest

from ti_cmax import so3
from ti_cmax.errors import InputError
from ti_cmax.metrics import (
    EvaluationConfig, default_t0, evaluate_rotations, evaluate_with_config, event_area_percent,
    gradient_magnitude, pan_angle_deg, relative_pair_starts, revolution_errors, rotation_angle_deg, smooth_trajectory,
    star_tracking_errors, worst_stretch,
)
from ti_cmax.trajectory import Trajectory

AXIS = np.array([1.0, 2.0, -2.0]) / 3.0  # unit axis


def _gt(rate=100.0, duration=4.0, t_start=0.0):
    """A rotating ground truth (more than 180 deg of yaw over 4 s) sampled at ``rate``."""
    t = t_start + np.arange(int(round(duration * rate)) + 1) / rate
    phi = np.stack([0.3 * np.sin(1.1 * t), 0.5 * np.sin(0.7 * t + 0.3), 0.9 * t], axis=1)
    return Trajectory(t, so3.exp(phi))


def test_rotation_angle_matches_eq23():
    r = so3.exp(np.array([[0.0, 0.0, 0.0], [0.1, -0.2, 0.3], [0.0, 3.0, 0.0]]))
    acos = np.degrees(np.arccos(np.clip((np.trace(r, axis1=1, axis2=2) - 1) / 2, -1, 1)))
    np.testing.assert_allclose(rotation_angle_deg(r), acos, atol=1e-6)
    np.testing.assert_allclose(rotation_angle_deg(r)[1], np.degrees(np.linalg.norm([0.1, -0.2, 0.3])))


def test_constant_offset_vanishes_after_alignment():
    gt = _gt()
    offset = so3.exp(np.radians(7.0) * AXIS)
    est = gt.left_multiplied(offset)
    res = evaluate_rotations(gt, est)
    assert res.t0 == pytest.approx(0.1)
    assert res.num_abs == len(gt) and res.abs_max_deg < 1e-6
    assert res.num_rel == 31 and res.rel_max_deg_per_s < 1e-6  # starts 0, 0.1, ..., 3.0
    raw = evaluate_rotations(gt, est, align=False)
    np.testing.assert_allclose(raw.abs_errors_deg, 7.0, atol=1e-9)
    assert raw.abs_rmse_deg == pytest.approx(7.0) and raw.rel_rmse_deg_per_s < 1e-6


def test_linear_drift_gives_k_deg_per_s():
    """est(t) = exp(k t a) gt(t): aligned abs error is exactly k |t - t0|, every relative error exactly k."""
    gt = _gt()
    k = np.radians(2.0)  # 2 deg/s
    est = Trajectory(gt.t, so3.exp(np.outer(k * gt.t, AXIS)) @ gt.R)
    res = evaluate_rotations(gt, est, t0=1.0)
    np.testing.assert_allclose(res.abs_errors_deg, 2.0 * np.abs(gt.t - 1.0), atol=1e-8)
    assert res.abs_rmse_deg == pytest.approx(np.sqrt(np.mean((2.0 * (gt.t - 1.0)) ** 2)))
    np.testing.assert_allclose(res.rel_errors_deg_per_s, 2.0, atol=1e-7)
    assert res.rel_rmse_deg_per_s == pytest.approx(2.0)
    # a 0.5 s delta still measures the rate (angle / delta)
    half = evaluate_rotations(gt, est, rel_delta=0.5)
    np.testing.assert_allclose(half.rel_errors_deg_per_s, 2.0, atol=1e-7)
    assert half.num_rel == 36


def test_white_noise_rmse_is_sigma_sqrt3():
    """Isotropic rotation-vector noise N(0, s^2 I3): E[angle^2] = 3 s^2; relative pairs: 6 s^2 / delta^2."""
    gt = _gt(rate=200.0, duration=20.0)
    sigma = 0.01
    noise = np.random.default_rng(0).normal(0.0, sigma, (len(gt), 3))
    est = Trajectory(gt.t, gt.R @ so3.exp(noise))
    res = evaluate_rotations(gt, est, align=False, rel_step=0.005)
    assert res.abs_rmse_deg == pytest.approx(np.degrees(sigma * np.sqrt(3.0)), rel=0.03)
    assert res.rel_rmse_deg_per_s == pytest.approx(np.degrees(sigma * np.sqrt(6.0)) / 1.0, rel=0.05)
    assert res.num_rel == len(gt) - 200


def test_t0_policy_overlap_and_rate():
    gt = _gt(duration=4.0)
    est = Trajectory(gt.t[50:300] + 0.001, gt.R[50:300])  # 0.501 .. 2.991 s
    assert default_t0(gt, est) == pytest.approx(0.601)
    assert default_t0(gt, est, offset=1.0) == pytest.approx(1.501)
    res = evaluate_rotations(gt, est, sample_rate=50.0)
    assert res.t_start == pytest.approx(0.501) and res.t_end == pytest.approx(2.991)
    np.testing.assert_allclose(np.diff(res.abs_times), 0.02)
    assert res.num_abs == 125 and res.abs_times[-1] <= res.t_end + 1e-9
    cfg = EvaluationConfig(t0_offset=1.0, sample_rate=50.0)
    assert evaluate_with_config(gt, est, cfg).t0 == pytest.approx(1.501)
    with pytest.raises(InputError, match="outside"):
        evaluate_rotations(gt, est, t0=0.2)
    with pytest.raises(InputError, match="do not overlap"):
        evaluate_rotations(gt, Trajectory(gt.t + 10.0, gt.R))
    short = evaluate_rotations(gt, Trajectory(gt.t[:50], gt.R[:50]))
    assert short.num_rel == 0 and short.to_dict()["rel_rmse_deg_per_s"] is None
    np.testing.assert_allclose(relative_pair_starts(0.0, 1.35, 1.0, 0.1), [0.0, 0.1, 0.2, 0.3])


def test_gt_filter_keeps_constant_rate_and_removes_noise():
    rng = np.random.default_rng(1)
    t = np.sort(np.concatenate([np.arange(0, 2.0, 0.005) + rng.uniform(0, 0.002, 400)]))
    w = np.array([0.4, -0.3, 1.5])
    steady = Trajectory(t, so3.exp(np.array([0.2, 0.1, 0.0])) @ so3.exp(np.outer(t, w)))
    smoothed = smooth_trajectory(steady, 0.05)
    assert np.max(rotation_angle_deg(np.swapaxes(smoothed.R, 1, 2) @ steady.R)) < 1e-6  # ends included

    clean = _gt(rate=200.0, duration=3.0)
    noisy = Trajectory(clean.t, clean.R @ so3.exp(rng.normal(0.0, 0.005, (len(clean), 3))))
    before = evaluate_rotations(clean, noisy, align=False).abs_rmse_deg
    after = evaluate_rotations(clean, smooth_trajectory(noisy, 0.05), align=False).abs_rmse_deg
    assert after < 0.5 * before
    # the same filter used through evaluate_rotations on the ground truth
    via = evaluate_rotations(noisy, clean, align=False, gt_filter_span=0.05).abs_rmse_deg
    assert via == pytest.approx(after, rel=1e-9)


def test_star_tracking_metric_on_drift():
    gt = _gt(duration=4.0)
    k = np.radians(0.5)
    est = Trajectory(gt.t, so3.exp(np.radians(30) * AXIS) @ so3.exp(np.outer(k * gt.t, AXIS)) @ gt.R)
    res = star_tracking_errors(gt, est)
    assert res.count == 10  # back-to-back 400 ms intervals in 4 s
    np.testing.assert_allclose(res.errors_deg, 0.5 * 0.4, atol=1e-8)
    assert res.rmse_deg == pytest.approx(0.2) and res.std_deg == pytest.approx(0.0, abs=1e-8)
    assert star_tracking_errors(gt, est, step=0.1).count == 37


def test_event_area_by_hand():
    h = np.array([[0.0, 1.0], [2.0, 0.0]])
    assert event_area_percent(h) == pytest.approx(100 * ((1 - np.exp(-1)) + (1 - np.exp(-2))) / 4)
    assert event_area_percent(h, lambda0=2.0) == pytest.approx(100 * ((1 - np.exp(-0.5)) + (1 - np.exp(-1))) / 4)
    assert event_area_percent(np.zeros((3, 4))) == 0.0


def test_gradient_magnitude_by_hand():
    ramp = np.tile(np.arange(3.0), (3, 1))  # I = x; borders replicated: |Ix| = 0.5, 1, 0.5 per row
    assert gradient_magnitude(ramp) == pytest.approx(np.sqrt(0.5))
    impulse = np.zeros((5, 5))
    impulse[2, 2] = 1.0  # Sobel taps 1,2,1 on each side, /8: sum of Ix^2 = sum of Iy^2 = 12/64
    assert gradient_magnitude(impulse) == pytest.approx(np.sqrt(24 / 64 / 25))
    assert gradient_magnitude(np.full((4, 6), 3.0)) == 0.0


def _evo_traj(traj):
    from evo.core.trajectory import PoseTrajectory3D

    q = np.roll(traj.quaternions_xyzw(), 1, axis=1)  # wxyz
    return PoseTrajectory3D(positions_xyz=np.zeros((len(traj), 3)), orientations_quat_wxyz=q,
                            timestamps=traj.t.copy())


def test_agrees_with_evo():
    pytest.importorskip("evo")
    from evo.core import metrics as evo_metrics

    gt = _gt(rate=100.0, duration=5.0)
    rng = np.random.default_rng(2)
    est = Trajectory(gt.t, so3.exp(np.outer(np.radians(1.5) * gt.t, AXIS)) @ gt.R
                     @ so3.exp(rng.normal(0.0, 0.01, (len(gt), 3))))
    res = evaluate_rotations(gt, est, rel_step=0.01)  # one pair per frame, as evo's all_pairs
    aligned = est.aligned_to(gt, res.t0)  # evo cannot align rotation-only trajectories itself

    ape = evo_metrics.APE(evo_metrics.PoseRelation.rotation_angle_deg)
    ape.process_data((_evo_traj(gt), _evo_traj(aligned)))
    np.testing.assert_allclose(res.abs_errors_deg, ape.error, atol=1e-6)

    rpe = evo_metrics.RPE(evo_metrics.PoseRelation.rotation_angle_deg, delta=100,
                          delta_unit=evo_metrics.Unit.frames, all_pairs=True)
    rpe.process_data((_evo_traj(gt), _evo_traj(aligned)))
    np.testing.assert_allclose(res.rel_errors_deg_per_s * res.rel_delta, rpe.error, atol=1e-6)


def test_evaluate_cli(tmp_path, capsys):
    from ti_cmax.cli import main
    from ti_cmax.io import write_tum

    gt = _gt(rate=100.0, duration=3.0)
    est = Trajectory(gt.t, so3.exp(np.outer(np.radians(2.0) * gt.t, AXIS)) @ gt.R)
    write_tum(tmp_path / "gt.txt", gt)
    write_tum(tmp_path / "est.txt", est)
    args = ["evaluate", "--groundtruth", str(tmp_path / "gt.txt"), "--estimate", str(tmp_path / "est.txt")]

    assert main(args) == 0
    last = capsys.readouterr().out.strip().splitlines()[-1]
    out = json.loads(last)
    expected = evaluate_rotations(gt, est)
    assert out["abs_rmse_deg"] == pytest.approx(expected.abs_rmse_deg, rel=1e-6)
    assert out["rel_rmse_deg_per_s"] == pytest.approx(2.0, rel=1e-6)
    assert out["t0"] == pytest.approx(0.1)

    assert main(args + ["--t0", "1.0", "--out", str(tmp_path / "res.json")]) == 0
    saved = json.loads((tmp_path / "res.json").read_text())
    assert saved["t0"] == 1.0 and saved["abs_rmse_deg"] == pytest.approx(
        evaluate_rotations(gt, est, t0=1.0).abs_rmse_deg, rel=1e-6)
    capsys.readouterr()
    assert main(args + ["--set", "rel_delta=0.5", "--set", "rel_step=0.25"]) == 0
    out = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert out["num_rel"] == 11 and out["rel_rmse_deg_per_s"] == pytest.approx(2.0, rel=1e-6)
    assert main(args + ["--set", "no_such_key=1"]) == 2
    capsys.readouterr()

    (tmp_path / "bad.txt").write_text("0.0 0 0 0 0 0 0 1\n0.1 0 0 zero 0 0 0 1\n")
    assert main(["evaluate", "--groundtruth", str(tmp_path / "bad.txt"),
                 "--estimate", str(tmp_path / "est.txt")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "bad.txt" in err[0]
    assert main(args + ["--t0", "50"]) == 2


def test_map_figures_by_row_blocks_equal_the_whole_image(monkeypatch):
    """EA, GM, variance and the PNG of large maps are computed by row blocks (bounded float64 temporaries: an
    8192x4096 HD map made `ti-cmax slam` peak at 1.7 GB); the result must not depend on the blocks."""
    from ti_cmax import metrics
    from ti_cmax.pipelines.panorama import PanoramaResult, map_to_uint8
    from ti_cmax.plots import map_display

    rng = np.random.default_rng(0)
    img = (rng.poisson(0.3, (61, 90)) * rng.uniform(0, 2, (61, 90))).astype(np.float32)
    gx, gy = metrics.image_gradient(img)
    whole = (100 * np.mean(-np.expm1(-img.astype(float))), np.sqrt(np.mean(gx * gx + gy * gy)),
             (np.clip(map_display(img, 0.75), 0, 1) * 255 + 0.5).astype(np.uint8), img.astype(float).var())
    monkeypatch.setattr(metrics, "BLOCK_PIXELS", 7 * 90)  # 9 blocks of 7 rows
    assert len(list(metrics.row_blocks(img.shape))) == 9
    fig = PanoramaResult(img, 1).figures()
    assert fig["event_area_percent"] == pytest.approx(whole[0], rel=1e-12)
    assert fig["gradient_magnitude"] == pytest.approx(whole[1], rel=1e-12)
    assert fig["variance"] == pytest.approx(whole[3], rel=1e-12)
    np.testing.assert_array_equal(map_to_uint8(img, 0.75), whole[2])


def test_evaluate_refuses_a_ground_truth_it_cannot_compare(tmp_path, capsys):
    """A ground truth in microseconds against an estimate in seconds gave 28.8 deg, a 2-pose one 8.8 deg, both with
    exit 0; now one line each (exit 2), and a comparable pair still scores."""
    from ti_cmax.cli import main
    from ti_cmax.io import write_tum

    t = np.arange(0.0, 2.0, 0.001)
    gt = Trajectory(t, so3.exp(np.outer(np.sin(3 * t), AXIS)))
    est = Trajectory(t[::5], gt.R[::5] @ so3.exp(np.radians(0.5) * np.array([1.0, 0.0, 0.0]))[None])
    paths = {}
    for name, traj in {"gt": gt, "est": est, "gt_us": Trajectory(t * 1e6, gt.R), "gt2": Trajectory(t[[0, 1990]],
                       gt.R[[0, 1990]]), "late": Trajectory(t + 5.0, gt.R)}.items():
        paths[name] = write_tum(tmp_path / f"{name}.txt", traj)
    cases = {
        "gt_us": r"the time ranges differ in scale: the ground truth's poses are 1e\+03 s apart \(median\), the "
                 r"estimate's 0.005 s \(2e\+05x\)",
        "gt2": r"the ground truth has 2 poses in the time range both trajectories cover \[0.000000, 1.990000\] s, at "
               r"least 3 are needed",
        "late": r"trajectories do not overlap in time",
    }
    for name, message in cases.items():
        assert main(["evaluate", "--groundtruth", str(paths[name]), "--estimate", str(paths["est"])]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and re.search(message, err[0]), err
    assert main(["evaluate", "--groundtruth", str(paths["gt"]), "--estimate", str(paths["est"])]) == 0
    assert "absolute RMSE: 0.3502 deg" in capsys.readouterr().out


# long recordings -----------------------------------------------------------------------------------------------
def _pan(turns=3.5, duration=35.0, rate=100.0, sign=1.0):
    """A pan about the world vertical (y) at a constant rate: R(t) = R_y(theta(t)); returns (trajectory, theta)."""
    t = np.arange(int(round(duration * rate)) + 1) / rate
    theta = sign * 2 * np.pi * turns * t / duration
    return Trajectory(t, so3.exp(np.outer(theta, [0.0, 1.0, 0.0]))), theta


def test_worst_stretch_finds_a_short_excursion():
    t = np.arange(1001) / 100.0
    e = np.full_like(t, 0.1)
    e[500:510] = 2.0  # 0.1 s at 2 deg, from 5.0 s
    rms, start = worst_stretch(t, e, 0.2)
    # every 0.2 s window holds 21 samples; the worst holds the 10 spike samples and 11 at 0.1 deg
    assert rms == pytest.approx(np.sqrt((10 * 4.0 + 11 * 0.01) / 21))
    assert 4.89 - 1e-9 <= start <= 5.0 + 1e-9  # windows from 4.89 s to 5.0 s hold the whole excursion
    assert worst_stretch(t, np.full_like(t, 0.3))[0] == pytest.approx(0.3)
    assert worst_stretch(t[:5], e[:5], 0.2)[0] == pytest.approx(0.1)  # shorter than the window: the whole range
    assert np.isnan(worst_stretch(np.zeros(0), np.zeros(0))[0])


def test_worst_stretch_of_an_estimate_that_snaps_back():
    """A 0.2 s excursion of 3 deg in 10 s: the RMSE dilutes it, the worst stretch shows it."""
    gt = _gt(duration=10.0)
    off = np.where((gt.t >= 6.0) & (gt.t < 6.2), np.radians(3.0), 0.0)
    est = Trajectory(gt.t, gt.R @ so3.exp(np.outer(off, AXIS)))
    err = evaluate_rotations(gt, est)
    assert err.abs_rmse_deg < 0.5
    rms, start = worst_stretch(err.abs_times, err.abs_errors_deg)
    assert rms == pytest.approx(3.0 * np.sqrt(20 / 21))
    assert 5.99 - 1e-9 <= start <= 6.0 + 1e-9  # the windows from 5.99 s and 6.0 s hold all 20 samples


def test_pan_angle_unwraps_over_turns():
    gt, theta = _pan(turns=2.5, duration=10.0)
    np.testing.assert_allclose(pan_angle_deg(gt, gt.t), np.degrees(theta), atol=1e-6)


def test_pan_angle_counts_turns_about_a_tilted_axis():
    """A pan about the camera's own y axis after a 120 deg tilt (as a long wobble leaves it): still 2.5 turns."""
    gt, theta = _pan(turns=2.5, duration=10.0)
    tilted = gt.left_multiplied(so3.exp(np.radians(120.0) * AXIS))
    np.testing.assert_allclose(pan_angle_deg(tilted, tilted.t), np.degrees(theta), atol=1e-6)
    np.testing.assert_allclose(pan_angle_deg(tilted, [2.5, 7.5]), [225.0, 675.0], atol=1e-6)


def test_an_error_that_follows_the_pan_swings_once_per_turn():
    """abs error 0.1 + 0.05 sin(theta): quarter-turn means 0.1 +- 0.05 * 2 / pi, the same every turn."""
    gt, theta = _pan()
    res = revolution_errors(gt, gt.t, 0.1 + 0.05 * np.sin(theta))
    assert res.complete == 3
    np.testing.assert_allclose(res.turns, [1.0, 1.0, 1.0, 0.5], atol=1e-9)
    np.testing.assert_allclose(res.sector_means_deg[:3], np.tile(0.1 + 0.1 / np.pi * np.array([1, 1, -1, -1]), (3, 1)),
                               atol=2e-4)
    assert np.isnan(res.sector_means_deg[3, 3])  # the half turn never reaches its last quarter
    assert res.swing_deg == pytest.approx(0.2 / np.pi, abs=5e-4)
    assert res.spread_deg < 1e-3
    assert res.to_dict()["sector_means_deg"][3][3] is None


def test_an_error_growing_per_turn_spreads_and_does_not_swing():
    gt, theta = _pan(sign=-1.0)  # the other direction: progress is counted along the pan
    res = revolution_errors(gt, gt.t, 0.1 + 0.02 * np.floor(np.abs(theta) / (2 * np.pi) + 1e-9))
    np.testing.assert_allclose(res.means_deg, [0.1, 0.12, 0.14, 0.16], atol=1e-9)
    assert res.spread_deg == pytest.approx(0.04) and res.swing_deg == pytest.approx(0.0, abs=1e-9)
    short, _ = _pan(turns=0.8, duration=8.0)
    none = revolution_errors(short, short.t, np.ones(len(short)))
    assert none.complete == 0 and np.isnan(none.swing_deg) and none.to_dict()["swing_deg"] is None
    with pytest.raises(InputError):
        revolution_errors(gt, gt.t, np.ones(len(gt)), sectors=0)


def test_revolution_errors_of_a_yaw_dependent_map_error():
    """An estimate tilted by 0.3 (1 - cos theta) deg, as a first turn's map error that later turns follow: after the
    start alignment the abs error is that tilt, its quarter-turn means swing by 0.3 * 4 / pi deg each turn."""
    gt, theta = _pan()
    tilt = np.radians(0.3) * (1 - np.cos(theta))
    est = Trajectory(gt.t, gt.R @ so3.exp(np.outer(tilt, [1.0, 0.0, 0.0])))
    err = evaluate_rotations(gt, est)
    res = revolution_errors(gt, err.abs_times, err.abs_errors_deg)
    assert res.swing_deg == pytest.approx(0.3 * 4 / np.pi, rel=0.02)
    assert res.spread_deg < 0.01
