"""Plot functions write non-empty PNG files (content is checked by eye, not here)."""
import numpy as np
import pytest

from ti_cmax import so3
from ti_cmax.plots import map_display, plot_error_distributions, plot_maps, plot_trajectories
from ti_cmax.trajectory import Trajectory

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def _is_png(path):
    data = path.read_bytes()
    return len(data) > 1000 and data[:8] == PNG_MAGIC


@pytest.mark.slow
def test_plot_trajectories(tmp_path):
    t = np.linspace(0.0, 3.0, 151)
    gt = Trajectory(t, so3.exp(np.stack([0.3 * np.sin(t), 0.2 * t, 2.5 * t], axis=1)))  # yaw passes 180 deg
    est = Trajectory(t[::5], gt.R[::5] @ so3.exp(np.full((31, 3), 0.02)))
    for rep in ("euler", "rotvec"):
        path = tmp_path / f"traj_{rep}.png"
        plot_trajectories(path, {"front-end": est, "BA": gt}, gt, representation=rep, title="test")
        assert _is_png(path)
    assert not list(tmp_path.glob(".*"))  # no temporary files left behind


@pytest.mark.slow
def test_plot_error_distributions(tmp_path):
    rng = np.random.default_rng(0)
    abs_err = {"a": rng.gamma(2.0, 0.5, 200), "b": rng.gamma(2.0, 1.0, 200), "one sample": np.array([1.0]),
               "empty": np.zeros(0)}
    rel_err = {k: v * 0.3 for k, v in abs_err.items()}
    plot_error_distributions(tmp_path / "err.png", abs_err, rel_err, title="errors")
    plot_error_distributions(tmp_path / "abs.png", {"a": abs_err["a"]})
    assert _is_png(tmp_path / "err.png") and _is_png(tmp_path / "abs.png")


def test_plot_maps(tmp_path):
    rng = np.random.default_rng(0)
    maps = {"GT": rng.poisson(0.3, (40, 80)).astype(float), "estimate": rng.poisson(0.6, (40, 80)).astype(float)}
    plot_maps(tmp_path / "maps.png", maps, title="maps")
    plot_maps(tmp_path / "one.png", [("empty", np.zeros((10, 20)))], show_metrics=False)
    assert _is_png(tmp_path / "maps.png") and _is_png(tmp_path / "one.png")
    disp = map_display(np.array([[0.0, 1.0], [4.0, 0.0]]), gamma=0.5)
    np.testing.assert_allclose(disp, [[1.0, 0.5], [0.0, 1.0]])


def test_maps_cropped_to_the_observed_region_across_the_seam():
    """A region straddling u = 0 stays one piece; the window holds every observed pixel and little else."""
    from ti_cmax.plots import observed_window

    img = np.zeros((100, 200))
    img[40:50, 190:200] = 1.0
    img[45:60, 0:15] = 2.0
    roll, rows, cols = observed_window([img, np.zeros_like(img)], margin=0.0)
    view = np.roll(img, roll, axis=1)[rows, cols]
    assert view.sum() == img.sum() and view.shape == (20, 25)
    roll, rows, cols = observed_window([img], margin=0.05)
    assert np.roll(img, roll, axis=1)[rows, cols].shape == (30, 45)
    assert observed_window([np.zeros((4, 8))]) == (0, slice(None), slice(None))


def test_map_contrast_stretch():
    """With a percentile peak, a few hot pixels no longer make the rest faint: they saturate (0, black)."""
    img = np.ones((10, 10))
    img[0, 0] = 1000.0
    faint = map_display(img, gamma=1.0)
    stretched = map_display(img, gamma=1.0, percentile=95.0)
    assert faint[5, 5] > 0.99 and stretched[5, 5] == 0.0 and stretched[0, 0] == 0.0


def test_plot_errors_over_time(tmp_path):
    from ti_cmax.metrics import evaluate_rotations
    from ti_cmax.plots import plot_errors_over_time

    t = np.linspace(0.0, 3.0, 301)
    gt = Trajectory(t, so3.exp(np.stack([0.3 * np.sin(t), 0.2 * t, 0.5 * t], axis=1)))
    est = Trajectory(t, gt.R @ so3.exp(np.outer(t, [0.01, 0.0, 0.0])))
    plot_errors_over_time(tmp_path / "e.png", {"drift": evaluate_rotations(gt, est)})
    assert _is_png(tmp_path / "e.png")


def test_cli_plot(tmp_path, capsys):
    import json

    from ti_cmax.cli import main
    from ti_cmax.io import write_tum
    from ti_cmax.metrics import evaluate_rotations

    t = np.linspace(0.0, 3.0, 301)
    gt = Trajectory(t, so3.exp(np.stack([0.3 * np.sin(t), 0.2 * t, 0.5 * t], axis=1)))
    paths = []
    for i, name in enumerate(("a", "b")):
        (tmp_path / name).mkdir()
        est = Trajectory(t, gt.R @ so3.exp(np.outer(t, [0.01 * (i + 1), 0.0, 0.0])))
        paths.append(write_tum(tmp_path / name / "trajectory.txt", est))
    write_tum(tmp_path / "gt.txt", gt)
    out = tmp_path / "plots"
    assert main(["plot", "--groundtruth", str(tmp_path / "gt.txt"), "--estimate", *map(str, paths),
                 "--out", str(out)]) == 0
    for name in ("trajectories.png", "errors_over_time.png", "errors.png"):
        assert _is_png(out / name), name
    summary = json.loads((out / "errors.json").read_text())
    assert list(summary) == ["a/trajectory", "b/trajectory"]  # same file names: the folder tells them apart
    from ti_cmax.io import read_tum

    expected = evaluate_rotations(gt, read_tum(paths[1])).abs_rmse_deg
    assert summary["b/trajectory"]["abs_rmse_deg"] == pytest.approx(expected)
    assert main(["plot", "--groundtruth", str(tmp_path / "gt.txt"), "--estimate", *map(str, paths),
                 "--labels", "only-one", "--out", str(tmp_path / "bad")]) == 2
    assert "expected 2 labels" in capsys.readouterr().err and not (tmp_path / "bad").exists()


def test_run_figure_without_and_with_ground_truth(tmp_path):
    """run.png of slam, frontend, refine and the baselines: readable without ground truth; with it also the error."""
    from types import SimpleNamespace

    from ti_cmax.plots import plot_run

    t = np.linspace(0.0, 2.0, 101)
    gt = Trajectory(t, so3.exp(np.stack([0.3 * np.sin(t), 0.2 * t, 1.5 * t], axis=1)))
    est = Trajectory(t[::2], gt.R[::2] @ so3.exp(np.full((51, 3), 0.01)))
    assert plot_run(tmp_path / "bare.png", est) == ["orientation", "angular velocity"]
    windows = [SimpleNamespace(t_start=0.2 * k, t_end=0.2 * k + 0.4, max_correction=0.001 * k, optimized=k != 3,
                               rejected=k == 3, still=False, skipped=False, cut_short=False) for k in range(8)]
    rate = (t, np.full_like(t, 1.5e6))
    panels = plot_run(tmp_path / "full.png", est, omega=(t, np.ones((101, 3))), windows=windows, event_rate=rate,
                      groundtruth=gt, title="run")
    assert panels == ["orientation", "angular velocity", "back-end", "event rate", "error"]
    assert _is_png(tmp_path / "bare.png") and _is_png(tmp_path / "full.png")
    # a ground truth that does not overlap the estimate: drawn without it
    far = Trajectory(t + 10.0, gt.R)
    assert "error" not in plot_run(tmp_path / "far.png", est, groundtruth=far)


def test_run_figure_imports_no_scipy_and_groups_the_windows(tmp_path):
    """run.png costs no scipy import (its angles come from so3) and one artist pair per window state, not per
    window (an artist per window cost ~0.1 s per figure of a 3 s run); the map-free figure modules stay light."""
    import subprocess
    import sys

    code = (
        "import sys, types, numpy as np\n"
        "from ti_cmax import so3\n"
        "from ti_cmax.plots import plot_run\n"
        "from ti_cmax.trajectory import Trajectory\n"
        "t = np.linspace(0.0, 2.0, 101)\n"
        "gt = Trajectory(t, so3.exp(np.stack([0.3 * np.sin(t), 0.2 * t, 1.5 * t], axis=1)))\n"
        "windows = [types.SimpleNamespace(t_start=0.1 * k, t_end=0.1 * k + 0.2, max_correction=0.001 * k,\n"
        "           optimized=k % 3 > 0, rejected=k % 3 == 0, still=False, skipped=False, cut_short=False)\n"
        "           for k in range(18)]\n"
        "import matplotlib.axes\n"
        "calls = []\n"
        "hlines = matplotlib.axes.Axes.hlines\n"
        "matplotlib.axes.Axes.hlines = lambda self, *a, **k: calls.append(1) or hlines(self, *a, **k)\n"
        f"plot_run({str(tmp_path / 'run.png')!r}, gt, windows=windows, groundtruth=gt, title='run')\n"
        "print(len(calls), 'scipy' in sys.modules)\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.split()
    assert out == ["2", "False"]  # two states (optimized, rejected): two line collections
    assert _is_png(tmp_path / "run.png")


def test_plot_command_without_ground_truth(tmp_path):
    from ti_cmax.cli import main
    from ti_cmax.io import write_tum

    t = np.linspace(0.0, 1.0, 51)
    write_tum(tmp_path / "est.txt", Trajectory(t, so3.exp(np.stack([0.1 * t, 0.5 * t, -t], axis=1))))
    assert main(["plot", "--estimate", str(tmp_path / "est.txt"), "--out", str(tmp_path / "figs"), "--quiet"]) == 0
    assert sorted(p.name for p in (tmp_path / "figs").iterdir()) == ["angular_velocity.png", "trajectories.png"]
    assert _is_png(tmp_path / "figs" / "trajectories.png")
