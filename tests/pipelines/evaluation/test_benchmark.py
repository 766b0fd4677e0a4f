"""``ti-cmax benchmark`` on a tiny suite: table structure, "not implemented" rows, output files, sequence cache."""
import csv
import json
import math
import re

import pytest

from ti_cmax.cli import main
from ti_cmax.errors import InputError
from ti_cmax.pipelines.evaluation import benchmark as B
from ti_cmax.pipelines.evaluation.methods import ba_source


def _rows(path):
    with open(path, newline="") as fh:
        return list(csv.DictReader(fh))


def _table(text: str, heading: str) -> list[str]:
    """Lines of the markdown table following ``heading``."""
    lines = text.splitlines()
    i = next(k for k, line in enumerate(lines) if line.startswith(heading))
    out = []
    for line in lines[i + 1:]:
        if line.startswith("|"):
            out.append(line)
        elif out:
            break
    return out


@pytest.mark.slow
def test_benchmark_tiny_suite(tmp_path, monkeypatch):
    # one registered baseline is hidden: it must appear as a "not implemented" row, never be dropped
    monkeypatch.delitem(B.BASELINES, "rtpt", raising=False)
    out = tmp_path / "bench"
    args = ["benchmark", "--out", str(out), "--sequences", "playroom", "--methods", "rtpt,cmax-omega,imu",
            "--quiet", "--set", "benchmark.duration=0.6", "--set", "pano_height=128",
            "--set", "benchmark.map_height=128", "--set", "benchmark.ba_degrees=1",
            "--set", "frontend_cg_max_iters=10", "--set", "backend_cg_max_iters=5"]
    assert main(args) == 0
    for name in ("tables.md", "results.csv", "results.json", "config.yaml", "plots/errors_playroom.png",
                 "plots/trajectories_playroom.png", "plots/maps_playroom.png"):
        assert (out / name).is_file(), name
    seqs = list((out / "sequences").iterdir())
    assert len(seqs) == 1 and (seqs[0] / "simulation.json").is_file() and (seqs[0] / "events.h5").is_file()

    rows = _rows(out / "results.csv")
    by = {r["method"]: r for r in rows}
    assert [r["method"] for r in rows] == [
        "ground truth", "RTPT", "CMax-omega", "IMU dead reckoning",
        "RTPT + BA (linear)", "CMax-omega + BA (linear)", "IMU dead reckoning + BA (linear)"]
    assert all(r["sequence"] == "playroom" and r["sensor"] == "DVS128" for r in rows)
    assert by["RTPT"]["status"] == "not implemented" and by["RTPT + BA (linear)"]["status"] == "not implemented"
    for name in ("CMax-omega", "IMU dead reckoning", "CMax-omega + BA (linear)", "IMU dead reckoning + BA (linear)"):
        r = by[name]
        assert r["status"] == "ok"
        assert 0 <= float(r["abs_rmse_deg"]) < 10
        assert 0 < float(r["ea_percent"]) < 100 and float(r["gm"]) > 0
    assert float(by["CMax-omega + BA (linear)"]["backend_us_per_event"]) > 0
    assert float(by["CMax-omega"]["frontend_us_per_event"]) > 0
    assert by["ground truth"]["abs_rmse_deg"] == "" and float(by["ground truth"]["ea_percent"]) > 0

    text = (out / "tables.md").read_text()
    tab2 = _table(text, "## Tab. II")
    assert tab2[0] == "| method | playroom abs | playroom rel |"
    assert [line.split("|")[1].strip() for line in tab2[2:]] == [r["method"] for r in rows[1:]]
    assert "| RTPT | not implemented |" in text
    assert "| RTPT + BA (linear) | not implemented |" in text
    tab4 = _table(text, "## Tab. IV")
    assert tab4[2].startswith("| ground truth |") and len(tab4) == 2 + len(rows)
    tab6 = _table(text, "## Tab. VI")
    assert len(tab6) == 3 and tab6[2].startswith("| playroom |")

    doc = json.loads((out / "results.json").read_text())
    assert doc["sequences"] == ["playroom"] and len(doc["results"][0]["rows"]) == len(rows)
    assert not doc["results"][0]["cached"]
    assert math.isfinite(doc["results"][0]["wall_seconds"])


@pytest.mark.slow
def test_lost_front_end_and_cache(tmp_path, monkeypatch):
    """A lost front-end shows "-" with a note, its BA is skipped; a raising one is an "error" row; the second run
    reuses the cached sequence."""
    from ti_cmax.pipelines.baselines import BaselineResult

    def lost_method(events, camera, config, imu):  # events: chunks streamed from the dataset
        from ti_cmax.pipelines.frontend import as_chunks
        from ti_cmax.trajectory import Trajectory
        import numpy as np

        t0 = next(iter(as_chunks(events))).t[0]
        t = np.linspace(t0, t0 + 0.2, 5)
        return BaselineResult(Trajectory(t, np.repeat(np.eye(3)[None], 5, axis=0)), np.zeros((4, 8)),
                              {"status": "lost", "lost_at": 0.2, "us_per_event": {"frontend": 1.0}})

    def broken_method(events, camera, config, imu, **extra):  # SMT entries also take contrast_threshold
        raise RuntimeError("boom")

    monkeypatch.setitem(B.BASELINES, "cmax-gae", lost_method)
    monkeypatch.setitem(B.BASELINES, "smt-pf", broken_method)
    cfg = B.BenchmarkConfig()
    from ti_cmax.config import update_config

    cfg = update_config(cfg, {"benchmark.duration": 0.3, "pano_height": 64, "benchmark.map_height": 64,
                              "benchmark.ba_degrees": "1"})
    spec = B.SUITE["playroom"]
    res = B.run_benchmark(cfg, [spec], ["cmax-gae", "smt-pf"], tmp_path, plots=False)
    by = {r["method"]: r for r in res[0]["rows"]}
    assert by["CMax-GAE"]["status"] == "lost" and by["CMax-GAE"]["abs_rmse_deg"] is None
    assert by["CMax-GAE"]["partial_abs_rmse_deg"] >= 0
    assert by["CMax-GAE + BA (linear)"]["status"] == "skipped"
    assert by["PF-SMT"]["status"] == "error" and "RuntimeError: boom" in by["PF-SMT"]["note"]
    assert by["PF-SMT + BA (linear)"]["status"] == "skipped"
    text = B.format_tables(res, {"map_height": 64})
    assert "| CMax-GAE | - [2] | - |" in text and "[2] CMax-GAE on playroom: lost, lost at 0.20 s" in text
    assert "| PF-SMT | - [1] | - |" in text and "[1] PF-SMT on playroom: error, RuntimeError: boom" in text
    # the runtime table keeps a lost run's figures (events processed until the loss), tagged; not an error's
    runtime = text.split("## Runtime of every method")[1]
    assert re.search(r"\| CMax-GAE \| 1\.00 \[2\] \| [0-9.]+ \|", runtime), runtime
    assert "| PF-SMT | - [1] | - |" in runtime
    again = B.run_benchmark(cfg, [spec], ["imu"], tmp_path, plots=False)
    assert again[0]["cached"] and again[0]["simulate_seconds"] == 0.0


def test_bad_selection():
    with pytest.raises(InputError):
        B.resolve_sequences(["nowhere"])
    with pytest.raises(InputError):
        B.resolve_methods(["orb-slam"])
    assert [s.name for s in B.resolve_sequences(None, quick=True)] == list(B.QUICK_SEQUENCES)
    assert B.resolve_methods(["cmax-slam", "imu"]) == ["imu", "cmax-slam"]


def test_ba_source_resampling():
    import numpy as np

    from ti_cmax import so3
    from ti_cmax.trajectory import Trajectory

    t = np.linspace(0.0, 1.0, 1001)  # 1 kHz
    traj = Trajectory(t, so3.exp(np.outer(t, [0.0, 0.3, 0.1])))
    out = ba_source(traj, 200.0)
    assert len(out) == 201 and out.t[0] == 0.0 and out.t[-1] == 1.0
    assert np.allclose(out.R, traj.at(out.t), atol=1e-9)
    assert ba_source(out, 200.0) is out and ba_source(traj, 0.0) is traj


def test_smoke_test_plots_say_so_in_their_titles(tmp_path, monkeypatch):
    """``benchmark --quick``'s figures must not read as the methods' accuracy: the note ends every title."""
    import numpy as np

    from ti_cmax.pipelines.evaluation import benchmark as bench
    from ti_cmax.trajectory import Trajectory

    titles = []
    for name in ("plot_error_distributions", "plot_trajectories", "plot_maps"):
        monkeypatch.setattr(bench, name, lambda *a, title="", **k: titles.append(title))
    traj = Trajectory(np.array([0.0, 1.0]), np.stack([np.eye(3)] * 2))
    arrays = {"cmax-slam": {"abs": np.zeros(3), "rel": np.zeros(3), "trajectory_aligned": traj,
                            "map": np.zeros((4, 8))}}
    bench.write_plots(tmp_path, "city", arrays, traj, "smoke test")
    assert len(titles) == 3 and all(t.endswith("(smoke test)") for t in titles)
