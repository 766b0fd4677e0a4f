"""The scripts in examples/ (one per kind of input, plus the CPU profile) run on small inputs and write what they
say: a user's first contact with the project must not be a broken example. They run in-process (runpy, shared
compiled kernels) except profile_cpu.py, which must start Taichi with its kernel profiler on."""
import re
import runpy
import subprocess
import sys
from pathlib import Path

import pytest

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"


def _run_example(name, args, monkeypatch, capsys):
    monkeypatch.setattr(sys, "argv", [name, *map(str, args)])
    runpy.run_path(str(EXAMPLES / name), run_name="__main__")
    return capsys.readouterr().out


@pytest.fixture(scope="module")
def sim_folder(tmp_path_factory, ti_runtime):
    """An ECD-layout folder (events.txt + events.h5, calib.txt, groundtruth.txt, imu.txt): DVS128, 1.5 s."""
    from ti_cmax.simulate import SimulatorConfig, simulate_sequence, write_sequence

    seq = simulate_sequence(SimulatorConfig(scene="town", sensor="DVS128", duration=1.5, max_angular_velocity=3.0,
                                            seed=3))
    folder = write_sequence(seq, tmp_path_factory.mktemp("examples") / "town_dvs128")
    return folder, seq


def _printed_rmse(out, label):
    m = re.search(rf"{label}\s+abs RMSE ([0-9.]+) deg", out)
    assert m, out
    return float(m.group(1))


@pytest.mark.slow
def test_ecd_folder_example(sim_folder, tmp_path, monkeypatch, capsys):
    folder, _ = sim_folder
    out = _run_example("ecd_folder.py", [folder, "--out", tmp_path / "ecd"], monkeypatch, capsys)
    for name in ("trajectory.txt", "angular_velocity.txt", "map.png", "report.json", "config.yaml"):
        assert (tmp_path / "ecd" / name).is_file(), name
    assert _printed_rmse(out, "CMax-SLAM") < 1.0  # scored from t0 = start + 1 s, as real data is


@pytest.mark.slow
def test_hdf5_example(sim_folder, tmp_path, monkeypatch, capsys):
    folder, seq = sim_folder
    out = _run_example("hdf5_file.py", [folder / "events.h5", "--out", tmp_path / "h5"], monkeypatch, capsys)
    assert f"{len(seq.events)} events" in out and "sensor 128x128" in out
    from ti_cmax.io import read_tum
    from ti_cmax.metrics import evaluate_rotations

    err = evaluate_rotations(seq.groundtruth, read_tum(tmp_path / "h5" / "slam_trajectory.txt"))
    assert err.abs_rmse_deg < 1.0
    assert (tmp_path / "h5" / "angular_velocity.txt").stat().st_size > 0


def test_ros_bag_example(sim_folder, tmp_path, monkeypatch, capsys, write_ros1_bag):
    folder, seq = sim_folder
    events = seq.events.slice_time(seq.events.t[0], seq.events.t[0] + 0.25)
    bag = write_ros1_bag(tmp_path / "town.bag", events, seq.camera, per_msg=5000)
    out = _run_example("ros_bag.py", [bag, "--out", tmp_path / "bag"], monkeypatch, capsys)
    assert f"{len(events)} events" in out
    from ti_cmax.io import read_tum

    traj = read_tum(tmp_path / "bag" / "trajectory.txt")
    assert traj.t[0] >= events.t[0] - 1e-6 and traj.t[-1] > events.t[0] + 0.15


@pytest.mark.slow
def test_simulated_sequence_example(tmp_path, monkeypatch, capsys, ti_runtime):
    out = _run_example("simulated_sequence.py", ["--sensor", "DVS128", "--scene", "bay", "--duration", "1.2",
                                                 "--out", tmp_path / "sim"], monkeypatch, capsys)
    rows = {m.group(1).strip(): float(m.group(2))
            for m in re.finditer(r"^(CMax-SLAM cubic|CMax-SLAM linear|IMU \+ BA)\s+([0-9.]+)", out, re.M)}
    assert len(rows) == 3 and max(rows.values()) < 1.0, out
    assert (tmp_path / "sim" / "trajectories.png").is_file() and (tmp_path / "sim" / "errors.png").is_file()


def test_real_ecd_slices_example(real_data, monkeypatch, capsys, ti_runtime):
    out = _run_example("real_ecd_slices.py", ["--data", real_data], monkeypatch, capsys)
    diffs = [float(d) for d in re.findall(r"\]\s+([0-9.]+)$", out, re.M)]
    assert diffs and max(diffs) < 10.0, out  # front-end vs ST-PPP, percent
    assert "windows refined" in out


@pytest.mark.slow
def test_profile_cpu_example(tmp_path):
    proc = subprocess.run([sys.executable, str(EXAMPLES / "profile_cpu.py"), "--duration", "0.4", "--sensor",
                           "DVS128", "--threads", "2"], capture_output=True, text=True, timeout=600, cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr[-2000:]
    out = proc.stdout
    assert "compile + warm-up" in out and "us/event" in out
    assert "Taichi kernels (steady state)" in out and re.search(r"k_\w+|vote|project", out), out[-2000:]


@pytest.mark.slow
def test_live_source_example(tmp_path, monkeypatch, capsys, ti_runtime):
    out = _run_example("live_source.py", ["--duration", "0.6", "--packet-us", "700", "--out", tmp_path / "live"],
                       monkeypatch, capsys)
    assert len(re.findall(r"events, refined$", out, re.M)) >= 4, out
    m = re.search(r"latest\(\) pose error while streaming: mean ([0-9.]+) deg, max ([0-9.]+) deg", out)
    assert m and float(m.group(2)) < 3.0, out
    final = re.search(r"final trajectory abs RMSE ([0-9.]+) deg", out)
    assert final and float(final.group(1)) < 1.0, out
    assert (tmp_path / "live" / "trajectory.txt").stat().st_size > 0


def test_docs_figures_composes_the_demo_picture(tmp_path):
    """docs_figures.py puts a demo's map above its error plot (the README's picture, regenerated by code)."""
    import imageio.v3 as iio
    import numpy as np

    demo = tmp_path / "demo_out"
    (demo / "slam").mkdir(parents=True)
    iio.imwrite(demo / "slam" / "map.png", np.full((60, 120), 200, np.uint8))
    iio.imwrite(demo / "errors_over_time.png", np.zeros((50, 100, 3), np.uint8))
    out = tmp_path / "demo.png"
    subprocess.run([sys.executable, str(EXAMPLES / "docs_figures.py"), "--demo-out", str(demo), "--out", str(out)],
                   check=True, capture_output=True)
    image = iio.imread(out)
    assert image.shape[0] > image.shape[1] / 2 and image.std() > 0  # two panels stacked, not blank
    assert (EXAMPLES.parent / "docs" / "img" / "demo.png").is_file()  # the README shows it


def test_viewer_screenshot_downscales_the_picture(tmp_path):
    """viewer_screenshot.py writes the browser's screenshot at the documentation's width (the capture itself needs
    a browser and runs by hand)."""
    import io

    import numpy as np
    from PIL import Image

    script = runpy.run_path(str(EXAMPLES / "viewer_screenshot.py"))
    rgb = np.zeros((1000, 1600, 3), np.uint8)
    rgb[:, 800:] = 255
    buf = io.BytesIO()
    Image.fromarray(rgb).save(buf, format="PNG")
    script["write_scaled"](buf.getvalue(), tmp_path / "viewer.png", 1200)
    image = np.asarray(Image.open(tmp_path / "viewer.png").convert("RGB"))
    assert image.shape == (750, 1200, 3)
    assert image[:, :590].max() < 10 and image[:, 610:].min() > 245
    assert script["free_port"]() > 0
