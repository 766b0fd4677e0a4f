"""The two kernel engines (taichi, quadrants): TI_CMAX_ENGINE chooses, --version and report.json name the engine,
and both give the same trajectory. Each run is a child process: the engine is imported once per process."""
import json
import os
import subprocess
import sys

import numpy as np
import pytest

from ti_cmax import __version__, so3
from ti_cmax.io import read_tum
from ti_cmax.kernels import engine
from ti_cmax.metrics import evaluate_rotations

INSTALLED = engine.installed_engines()
both_engines = pytest.mark.skipif(len(INSTALLED) < 2, reason="needs taichi and quadrants installed")


def _run(args, engine_name=None, **env):
    environ = {**os.environ, **env}
    environ.pop("TI_CMAX_ENGINE", None)
    if engine_name:
        environ["TI_CMAX_ENGINE"] = engine_name
    return subprocess.run([sys.executable, *args], capture_output=True, text=True, timeout=300, env=environ)


def test_the_default_is_taichi_where_installed_else_quadrants(monkeypatch):
    import importlib.util

    monkeypatch.delenv("TI_CMAX_ENGINE", raising=False)
    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name: real(name) if name != "taichi" else object())
    assert engine.engine_name() == "taichi"
    monkeypatch.setattr(importlib.util, "find_spec", lambda name: real(name) if name != "taichi" else None)
    assert engine.engine_name() == "quadrants"
    monkeypatch.setenv("TI_CMAX_ENGINE", " Quadrants ")
    assert engine.engine_name() == "quadrants"


@pytest.mark.parametrize("name", INSTALLED)
def test_the_environment_variable_chooses_the_engine_and_version_names_it(name):
    code = ("import sys; from ti_cmax.kernels import runtime; "
            "print(runtime.ENGINE, runtime.ti.__name__, sorted({'taichi', 'quadrants'} & set(sys.modules)))")
    proc = _run(["-c", code], name)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.split() == [name, name, f"['{name}']"]  # the other engine is not imported
    # --version reads the installed distribution's metadata: no engine import
    code = ("import sys; from ti_cmax.cli import version_text; print(version_text()); "
            "print(sorted({'taichi', 'quadrants'} & set(sys.modules)))")
    proc = _run(["-c", code], name)
    version = engine.engine_version(name)
    assert proc.returncode == 0 and proc.stdout.splitlines() == [f"ti-cmax {__version__} ({name} {version})", "[]"]
    proc = _run(["-m", "ti_cmax.cli", "--version"], name)
    assert proc.returncode == 0 and proc.stdout.strip().endswith(f"({name} {version})")


def test_a_bad_or_missing_engine_is_one_error_line(tmp_path):
    for args in (["--version"], ["slam", str(tmp_path), "--out", str(tmp_path / "out"), "--threads", "1"]):
        proc = _run(["-m", "ti_cmax.cli", *args], "cuda")
        assert proc.returncode == 2 and proc.stdout == ""
        assert proc.stderr.strip().splitlines() == [
            f"ti-cmax{' slam' if args[0] == 'slam' else ''}: error: TI_CMAX_ENGINE='cuda': expected one of "
            "taichi, quadrants"]
    # an engine that is not installed (its import blocked)
    code = ("import sys; sys.modules['quadrants'] = None; from ti_cmax.cli import main; "
            f"sys.exit(main(['slam', {str(tmp_path)!r}, '--out', {str(tmp_path / 'out')!r}, '--threads', '1']))")
    proc = _run(["-c", code], "quadrants")
    assert proc.returncode == 2 and "Traceback" not in proc.stderr
    assert proc.stderr.strip() == ("ti-cmax slam: error: kernel engine quadrants is not installed "
                                   "(pip install 'ti-cmax[quadrants]')")
    assert not (tmp_path / "out").exists()


def _slam(dataset, out, name, fast_math):
    proc = _run(["-m", "ti_cmax.cli", "slam", str(dataset), "--out", str(out), "--quiet", "--threads", "1",
                 "--set", "pano_height=256"], name, TI_CMAX_FAST_MATH=fast_math)
    assert proc.returncode == 0, proc.stderr
    report = json.loads((out / "report.json").read_text())
    assert report["engine"] == {"name": name, "version": engine.engine_version(name)}
    return {f: (out / f).read_bytes() for f in ("trajectory.txt", "angular_velocity.txt", "map.npy")}


@both_engines
def test_the_engines_agree_bit_for_bit_without_fast_math(engine_dataset, tmp_path):
    """One thread, fast math off: the same bytes from both engines (their LLVM releases round alike then)."""
    taichi, quadrants = (_slam(engine_dataset, tmp_path / name, name, "0") for name in ("taichi", "quadrants"))
    assert taichi == quadrants


@both_engines
def test_the_engines_agree_within_a_tolerance_with_fast_math(engine_dataset, tmp_path):
    """One thread, fast math on (the default): kernel results ~1 ulp apart, amplified by the optimizers along the
    run, yet the trajectories stay within 0.15 deg of each other (measured: 0.05 deg at most) and both as accurate."""
    for name in ("taichi", "quadrants"):
        _slam(engine_dataset, tmp_path / name, name, "1")
    taichi, quadrants = (read_tum(tmp_path / name / "trajectory.txt") for name in ("taichi", "quadrants"))
    np.testing.assert_array_equal(taichi.t, quadrants.t)
    assert np.degrees(so3.geodesic_angle(taichi.R, quadrants.R).max()) < 0.15
    gt = read_tum(engine_dataset / "groundtruth.txt")
    errors = [evaluate_rotations(gt, t).abs_rmse_deg for t in (taichi, quadrants)]
    assert max(errors) < 0.3 and abs(errors[0] - errors[1]) < 0.05  # measured: 0.141, 0.146 deg


@pytest.mark.slow
@both_engines
def test_the_per_event_benchmark_gives_a_row_per_engine(tmp_path, monkeypatch, capsys):
    from ti_cmax.pipelines.evaluation import bench_sensors
    from ti_cmax.pipelines.evaluation.benchmark import SUITES, SequenceSpec

    tiny = SequenceSpec("tiny", "DVS128", "town", 0.25, 2)
    monkeypatch.setitem(SUITES, "sensors", {"tiny": tiny})
    assert bench_sensors.main(["--out", str(tmp_path), "--sensors", "tiny", "--threads", "1",
                               "--set", "pano_height=128"]) == 0
    rows = json.loads((tmp_path / "sensors.json").read_text())
    assert [r["engine"] for r in rows] == [f"{name} {engine.engine_version(name)}" for name in INSTALLED]
    assert all(r["frontend_us_per_event"] > 0 and r["backend_us_per_event"] > 0 for r in rows)
    table = (tmp_path / "sensors.md").read_text().splitlines()
    assert "| engine |" in table[0] and [line.split(" | ")[1] for line in table[2:4]] == [r["engine"] for r in rows]
    assert (tmp_path / "runs" / "tiny" / "quadrants" / "trajectory.txt").is_file()
    capsys.readouterr()
    with pytest.raises(SystemExit):
        bench_sensors.main(["--out", str(tmp_path), "--engines", "cuda"])
    assert "--engines" in capsys.readouterr().err
