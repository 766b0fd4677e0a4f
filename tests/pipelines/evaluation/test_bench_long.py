"""The minute-long suite: its declaration, the table of bench_long and the long-recording section of
``ti-cmax benchmark``'s tables."""
import numpy as np
import pytest

from ti_cmax import so3
from ti_cmax.config import update_config
from ti_cmax.errors import InputError
from ti_cmax.pipelines.evaluation import bench_long
from ti_cmax.pipelines.evaluation import benchmark as B
from ti_cmax.pipelines.evaluation.methods import BenchmarkSettings, _simulator_config
from ti_cmax.trajectory import Trajectory


def test_long_suite_is_minute_long_multi_turn_pans_with_sensor_defects():
    specs = B.resolve_sequences(None, suite="long")
    assert len(specs) == 3 and len({s.seed for s in specs}) == 3
    for spec in specs:
        sim = _simulator_config(spec, BenchmarkSettings())
        assert (sim.sensor, sim.duration, sim.trajectory) == ("DAVIS240C", 60.0, "pan")
        assert sim.turns == pytest.approx(3.7) and sim.pan_wobble == pytest.approx(1.0)
        assert sim.threshold_sigma > 0 and sim.refractory_period > 0 and sim.noise_rate > 0 and sim.hot_pixels > 0
    assert B.resolve_methods(None, "long") == ["cmax-slam"]


def _pan_with_excursion():
    """A 2.5-turn pan over 20 s and an estimate 2 deg off for 0.2 s at 12 s."""
    t = np.arange(2001) / 100.0
    gt = Trajectory(t, so3.exp(np.outer(2 * np.pi * 2.5 * t / 20.0, [0.0, 1.0, 0.0])))
    off = np.where((t >= 12.0) & (t < 12.2), np.radians(2.0), 0.0)
    return gt, Trajectory(t, gt.R @ so3.exp(np.outer(off, [1.0, 0.0, 0.0])))


def test_score_run_and_table():
    gt, est = _pan_with_excursion()
    loops = [{"accepted": True, "applied": True}, {"accepted": True, "applied": False}, {"accepted": False}]
    res = bench_long.score_run(gt, est, {"loops": loops, "status": "ok"})
    assert res["abs_rmse_deg"] < 0.3 and res["worst_stretch_deg"] == pytest.approx(2.0 * np.sqrt(20 / 21))
    assert 11.99 - 1e-9 <= res["worst_stretch_at_s"] <= 12.0 + 1e-9
    assert (res["loops_applied"], res["loops_accepted"], res["loops_candidates"]) == (1, 1 + 1, 3)
    turns = res["revolutions"]
    assert turns["complete"] == 2 and len(turns["means_deg"]) == 3
    # the excursion (at 1.5 turns, in turn 1's third quarter) is the only error: turn 1 swings, turn 0 does not
    assert turns["swing_deg"] == pytest.approx(max(turns["sector_means_deg"][1]))
    row = {"sequence": "pan", "event_rate_mev_s": 0.5, "offline": {**res, "process_wall_seconds": 40.0,
                                                                   "peak_rss_mb": 900.0, "load_1min": [1.0, 2.0]}}
    table = bench_long.format_table([row])
    line = table.splitlines()[2]
    assert line.startswith("| pan | offline | 0.50 | ") and "| 1 / 2 / 3 |" in line
    assert line.endswith("| 40.0 | 900 | 1.0-2.0 |")
    assert f"| {res['worst_stretch_deg']:.3f} (12.0) |" in line or f"| {res['worst_stretch_deg']:.3f} (11.9) |" in line


def test_unknown_recording_is_refused(tmp_path, capsys):
    with pytest.raises(InputError):
        bench_long.run(tmp_path, ["nowhere"])
    assert bench_long.main(["--out", str(tmp_path), "--sequences", "nowhere"]) == 2
    assert capsys.readouterr().err.startswith("error: --sequences: unknown nowhere")


def test_benchmark_tables_show_long_recording_figures(tmp_path):
    """A short multi-turn pan through the task model: rows carry the worst stretch and the swing, tables.md has the
    long-recording section (IMU dead reckoning: the cheapest method)."""
    spec = B.SequenceSpec("pan", "DVS128", "city", 0.5, 0, trajectory="pan", options=(("turns", 1.2),))
    cfg = update_config(B.BenchmarkConfig(), {"benchmark.map_height": 16})
    res = B.run_benchmark(cfg, [spec], ["imu"], tmp_path, plots=False)
    imu = next(r for r in res[0]["rows"] if r["key"] == "imu")
    assert imu["status"] == "ok" and imu["worst_stretch_deg"] >= imu["abs_rmse_deg"] > 0
    assert imu["turn_swing_deg"] >= 0 and len(imu["turn_means_deg"]) == 2
    text = B.format_tables(res, {"map_height": 16})
    section = text.split("## Long recordings")[1].split("## Tab. IV")[0]
    assert "| method | pan worst 0.2 s | pan swing | pan loops |" in section
    assert f"| IMU dead reckoning | {imu['worst_stretch_deg']:.3f} | {imu['turn_swing_deg']:.3f} | - |" in section
    short = [{**res[0], "rows": [{**r, "turn_swing_deg": None} for r in res[0]["rows"]]}]
    assert "## Long recordings" not in B.format_tables(short, {"map_height": 16})
