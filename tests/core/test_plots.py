"""Plot functions write non-empty PNG files (content is checked by eye, not here)."""
import numpy as np

from ti_cmax import so3
from ti_cmax.plots import map_display, plot_error_distributions, plot_maps, plot_trajectories
from ti_cmax.trajectory import Trajectory

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def _is_png(path):
    data = path.read_bytes()
    return len(data) > 1000 and data[:8] == PNG_MAGIC


def test_plot_trajectories(tmp_path):
    t = np.linspace(0.0, 3.0, 151)
    gt = Trajectory(t, so3.exp(np.stack([0.3 * np.sin(t), 0.2 * t, 2.5 * t], axis=1)))  # yaw passes 180 deg
    est = Trajectory(t[::5], gt.R[::5] @ so3.exp(np.full((31, 3), 0.02)))
    for rep in ("euler", "rotvec"):
        path = tmp_path / f"traj_{rep}.png"
        plot_trajectories(path, {"front-end": est, "BA": gt}, gt, representation=rep, title="test")
        assert _is_png(path)
    assert not list(tmp_path.glob(".*"))  # no temporary files left behind


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
