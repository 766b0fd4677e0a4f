"""Outputs under faults: all-or-nothing folders and files, one writer per folder, one error line per OS failure
(not a folder, no permission, disk full), no crash when HDF5 meets a full disk."""
import os
import signal
import subprocess
import sys
import textwrap
import time

import numpy as np
import pytest

from ti_cmax.cli import main
from ti_cmax.errors import OutputError
from ti_cmax.outputs import PARTIAL_PREFIX, OutputDir, atomic_files


def _listing(folder):
    return {p.name: p.read_text() for p in folder.iterdir()}


def _tum(path, n=30):
    path.write_text("".join(f"{0.1 * i:.1f} 0 0 0 0 0 0 1\n" for i in range(n)))
    return path


def test_output_dir_moves_the_whole_set_in_only_on_success(tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    (out / "a.txt").write_text("old a")
    (out / "b.txt").write_text("old b")
    (out / "sub").mkdir()
    (out / "sub" / "x").write_text("old x")
    for failure in (RuntimeError, KeyboardInterrupt):
        with pytest.raises(failure):
            with OutputDir(out) as d:
                assert d != out and d.parent == out
                (d / "a.txt").write_text("new a")
                (d / "c.txt").write_text("new c")
                raise failure
        assert sorted(os.listdir(out)) == ["a.txt", "b.txt", "sub"]
        assert (out / "a.txt").read_text() == "old a" and not (out / "c.txt").exists()
    with OutputDir(out) as d:
        (d / "a.txt").write_text("new a")
        (d / "sub").mkdir()
        (d / "sub" / "y").write_text("new y")
    assert sorted(os.listdir(out)) == ["a.txt", "b.txt", "sub"]
    assert (out / "a.txt").read_text() == "new a" and (out / "b.txt").read_text() == "old b"
    assert os.listdir(out / "sub") == ["y"]  # a folder of the set replaces the old one whole


def test_a_failed_first_run_leaves_no_folder(tmp_path):
    out = tmp_path / "new" / "out"
    with pytest.raises(ValueError):
        with OutputDir(out) as d:
            (d / "a.txt").write_text("x")
            raise ValueError
    assert os.listdir(tmp_path) == []


def test_a_ctrl_c_while_the_partial_folder_is_made_leaves_nothing(tmp_path, monkeypatch):
    """A Ctrl-C landing right after the hidden folder was created (before the command writes) left that folder in
    the output folder."""
    out = tmp_path / "out"
    out.mkdir()
    (out / "kept.txt").write_text("previous")

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(os, "chmod", interrupted)
    with pytest.raises(KeyboardInterrupt):
        with OutputDir(out):
            pass
    assert os.listdir(out) == ["kept.txt"]


def test_a_second_run_into_the_same_folder_refuses(tmp_path):
    out = tmp_path / "out"
    with OutputDir(out) as d:
        (d / "first.txt").write_text("1")
        with pytest.raises(OutputError, match="another ti-cmax run is writing to this folder"):
            with OutputDir(out):
                pass
    assert os.listdir(out) == ["first.txt"]
    with OutputDir(out) as d:  # the lock ends with the run
        (d / "second.txt").write_text("2")
    assert sorted(os.listdir(out)) == ["first.txt", "second.txt"]


def test_the_partial_folder_of_a_killed_run_is_removed_by_the_next(tmp_path):
    out = tmp_path / "out"
    (out / (PARTIAL_PREFIX + "dead")).mkdir(parents=True)
    (out / (PARTIAL_PREFIX + "dead") / "events.h5").write_bytes(b"truncated")
    with OutputDir(out) as d:
        (d / "a.txt").write_text("x")
    assert os.listdir(out) == ["a.txt"]


def test_atomic_files_replace_all_or_none(tmp_path):
    a, b = tmp_path / "m.png", tmp_path / "m.json"
    a.write_text("old png")
    b.write_text("old json")
    with pytest.raises(RuntimeError):
        with atomic_files(a, b) as (ta, tb):
            ta.write_text("new png")
            raise RuntimeError
    assert (a.read_text(), b.read_text()) == ("old png", "old json") and sorted(os.listdir(tmp_path)) == \
        ["m.json", "m.png"]
    with atomic_files(a, b) as (ta, tb):
        ta.write_text("new png")
        tb.write_text("new json")
    assert (a.read_text(), b.read_text()) == ("new png", "new json")


def _one_error_line(err: str, *parts: str) -> None:
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in err, err
    for part in parts:
        assert part in lines[0], (part, lines[0])


def test_a_folder_given_for_a_file_is_one_line(tmp_path, capsys):
    gt = _tum(tmp_path / "gt.txt")
    folder = tmp_path / "folder"
    folder.mkdir()
    assert main(["map", str(tmp_path / "missing"), "--trajectory", str(gt), "--out", str(folder)]) == 2
    _one_error_line(capsys.readouterr().err, "ti-cmax map: error:", str(folder), "is a folder")
    assert main(["evaluate", "--groundtruth", str(gt), "--estimate", str(gt), "--out", str(folder)]) == 2
    _one_error_line(capsys.readouterr().err, "ti-cmax evaluate: error:", str(folder), "is a folder")
    assert os.listdir(folder) == []


def test_an_output_below_a_file_is_one_line(tmp_path, capsys):
    gt = _tum(tmp_path / "gt.txt")
    est = tmp_path / "est.txt"
    est.write_text(gt.read_text())
    assert main(["evaluate", "--groundtruth", str(gt), "--estimate", str(est), "--out", str(gt / "e.json")]) == 2
    _one_error_line(capsys.readouterr().err, "ti-cmax evaluate: error:", str(gt), "Not a directory")
    assert main(["plot", "--groundtruth", str(gt), "--estimate", str(est), "--out", str(gt / "plots")]) == 2
    _one_error_line(capsys.readouterr().err, "ti-cmax plot: error:", str(gt), "Not a directory")
    assert sorted(os.listdir(tmp_path)) == ["est.txt", "gt.txt"]


@pytest.fixture
def unwritable(tmp_path):
    """A folder this process cannot write in: a read-only one, or for root (which ignores modes) /sys."""
    if os.geteuid() != 0:
        d = tmp_path / "ro"
        d.mkdir()
        d.chmod(0o555)
        yield d
        d.chmod(0o755)
    elif os.path.isdir("/sys"):
        yield type(tmp_path)("/sys")
    else:
        pytest.skip("no folder this process cannot write")


def test_a_folder_that_cannot_be_written_is_one_line(tmp_path, unwritable, capsys):
    gt = _tum(tmp_path / "gt.txt")
    assert main(["evaluate", "--groundtruth", str(gt), "--estimate", str(gt), "--out",
                 str(unwritable / "e.json")]) == 2
    _one_error_line(capsys.readouterr().err, "ti-cmax evaluate: error:", str(unwritable))
    assert main(["plot", "--groundtruth", str(gt), "--estimate", str(gt), "--out", str(unwritable / "p")]) == 2
    _one_error_line(capsys.readouterr().err, "ti-cmax plot: error:", str(unwritable))
    assert not (unwritable / "e.json").exists() and not (unwritable / "p").exists()


def _small_sequence(folder, n=20_000, seed=0):
    from ti_cmax.camera import Camera
    from ti_cmax.events import Events
    from ti_cmax.io import write_calib_txt, write_events_h5

    rng = np.random.default_rng(seed)
    folder.mkdir(parents=True)
    camera = Camera(240, 180, 199.0, 199.0, 120.0, 90.0)
    ev = Events(np.sort(rng.uniform(0, 1, n)), rng.integers(0, 240, n).astype(np.uint16),
                rng.integers(0, 180, n).astype(np.uint16), rng.integers(0, 2, n).astype(np.int8) * 2 - 1)
    write_events_h5(folder / "events.h5", ev, camera=camera)
    write_calib_txt(folder / "calib.txt", camera)
    return folder


def _run_with_file_size_limit(args, limit):
    """``ti-cmax ARGS`` in a process whose files cannot grow beyond ``limit`` bytes: a full disk for the writer
    (SIGXFSZ ignored, so a write beyond the limit fails with EFBIG as one on a full disk fails with ENOSPC)."""
    code = textwrap.dedent(f"""
        import resource, signal, sys
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, ({limit}, {limit}))
        from ti_cmax.cli import main
        sys.exit(main({list(map(str, args))!r}))
    """)
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120,
                          env={**os.environ, "TI_CMAX_NO_PROGRESS": "1"})


@pytest.mark.parametrize("name", ["out.h5", "out.txt"])
def test_convert_on_a_full_disk_is_one_line_and_no_file(tmp_path, name):
    """HDF5 on a full disk crashed the process at exit (segmentation fault, exit 139); text ended in a traceback."""
    seq = _small_sequence(tmp_path / "seq")
    dest = tmp_path / "dest"
    dest.mkdir()
    res = _run_with_file_size_limit(["convert", seq, dest / name, "--quiet"], 100_000)
    assert res.returncode == 2, (res.returncode, res.stderr[-2000:])
    _one_error_line(res.stderr, "ti-cmax convert: error:", str(dest / name), "File too large")
    assert os.listdir(dest) == []


def test_simulate_on_a_full_disk_is_one_line_and_keeps_the_previous_sequence(tmp_path):
    out = tmp_path / "sim"
    out.mkdir()
    (out / "events.h5").write_text("previous")
    res = _run_with_file_size_limit(["simulate", out, "--duration", "0.1", "--quiet"], 200_000)
    assert res.returncode == 2, (res.returncode, res.stderr[-2000:])
    _one_error_line(res.stderr, "ti-cmax simulate: error:", str(out / "events.h5"), "File too large")
    assert _listing(out) == {"events.h5": "previous"}


def test_simulate_killed_leaves_the_previous_sequence_whole(tmp_path):
    """SIGKILL of simulate left a corrupt events.h5 under its final name."""
    out = tmp_path / "sim"
    out.mkdir()
    (out / "events.h5").write_text("previous")
    proc = subprocess.Popen([sys.executable, "-m", "ti_cmax.cli", "simulate", str(out), "--duration", "5", "--quiet"],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:  # until the run writes events into its partial folder
            if any(p.name == "events.h5" and p.stat().st_size > 0 for p in out.glob(PARTIAL_PREFIX + "*/*")):
                break
            time.sleep(0.05)
        else:
            pytest.fail("simulate wrote nothing within 60 s")
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=30)
    finally:
        proc.kill()
    assert (out / "events.h5").read_text() == "previous"
    with OutputDir(out) as d:  # the next run removes the killed one's partial folder
        (d / "x").write_text("")
    assert sorted(os.listdir(out)) == ["events.h5", "x"]


def test_commands_refuse_an_output_folder_another_run_is_writing(tmp_path, capsys):
    """Two runs into one --out both succeeded and interleaved their files."""
    from ti_cmax.outputs import OutputLock

    seq = _small_sequence(tmp_path / "seq")
    out = tmp_path / "out"
    with OutputLock(out):
        for args in (["slam", seq, "--out", out, "--sequential"], ["frontend", seq, "--out", out],
                     ["benchmark", "--out", out, "--quick"], ["sweep", "--out", out]):
            assert main([str(a) for a in args] + ["--quiet"]) == 2, args
            _one_error_line(capsys.readouterr().err, f"ti-cmax {args[0]}: error:", str(out),
                            "another ti-cmax run is writing to this folder")
        assert os.listdir(out) == []


@pytest.mark.parametrize("sig, code", [(signal.SIGTERM, 143), (signal.SIGINT, 130)])
def test_a_rerun_interrupted_leaves_the_previous_outputs_whole(tmp_path, sig, code):
    """A rerun into an existing --out stopped by SIGTERM left its new trajectory and a truncated map.npy beside the
    previous config.yaml and report.json."""
    seq = _small_sequence(tmp_path / "seq", n=2_000_000)  # seconds of work: the signal lands before the end
    out = tmp_path / "out"
    out.mkdir()
    previous = {"config.yaml": "previous config", "report.json": "{}", "trajectory.txt": "previous"}
    for name, text in previous.items():
        (out / name).write_text(text)
    proc = subprocess.Popen([sys.executable, "-m", "ti_cmax.cli", "frontend", str(seq), "--out", str(out), "--quiet"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env={**os.environ, "TI_CMAX_NO_PROGRESS": "1"})
    try:
        deadline = time.monotonic() + 60
        while not any(out.glob(PARTIAL_PREFIX + "*")) and proc.poll() is None and time.monotonic() < deadline:
            time.sleep(0.02)
        assert proc.poll() is None, "the run ended before it could be interrupted"
        proc.send_signal(sig)
        _, err = proc.communicate(timeout=60)
    finally:
        proc.kill()
    assert proc.returncode == code, err
    assert _listing(out) == previous


def test_a_rerun_failing_while_it_writes_leaves_the_previous_outputs_whole(tmp_path, monkeypatch, capsys):
    """Interrupted between two of its files, a rerun had replaced the first ones: the folder mixed two runs."""
    from ti_cmax import config

    seq = _small_sequence(tmp_path / "seq")
    out = tmp_path / "out"
    out.mkdir()
    previous = {"config.yaml": "previous config", "angular_velocity.txt": "previous", "trajectory.txt": "previous"}
    for name, text in previous.items():
        (out / name).write_text(text)

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(config, "save_config", interrupted)  # after angular_velocity.txt and trajectory.txt
    assert main(["frontend", str(seq), "--out", str(out), "--quiet"]) == 130
    assert _listing(out) == previous


def test_frontend_on_a_full_disk_is_one_line_and_keeps_the_previous_outputs(tmp_path):
    """slam, frontend and text outputs on a full disk ended in a traceback."""
    seq = _small_sequence(tmp_path / "seq")
    out = tmp_path / "out"
    out.mkdir()
    (out / "trajectory.txt").write_text("previous")
    res = _run_with_file_size_limit(["frontend", seq, "--out", out, "--quiet"], 2000)
    assert res.returncode == 2, (res.returncode, res.stderr[-2000:])
    _one_error_line(res.stderr, "ti-cmax frontend: error:", str(out), "File too large")
    assert _listing(out) == {"trajectory.txt": "previous"}


def test_slam_whose_run_figure_meets_a_full_disk_is_one_line_and_keeps_the_previous_outputs(tmp_path):
    """run.png is written by the figure process (ti_cmax/figure_process.py): its error is the command's one line,
    and nothing of the run is left (the other outputs, smaller than the limit, were written)."""
    seq = _small_sequence(tmp_path / "seq")
    out = tmp_path / "out"
    out.mkdir()
    (out / "trajectory.txt").write_text("previous")
    res = _run_with_file_size_limit(["slam", seq, "--out", out, "--quiet", "--set", "pano_height=64"], 60_000)
    assert res.returncode == 2, (res.returncode, res.stderr[-2000:])
    _one_error_line(res.stderr, "ti-cmax slam: error:", str(out), "File too large")
    assert _listing(out) == {"trajectory.txt": "previous"}


def test_any_os_error_of_a_command_is_one_line(monkeypatch, capsys):
    """A file that vanishes while a command reads it (or any other OS failure) ended in a traceback."""
    from ti_cmax.commands import info

    def vanished(args):
        raise FileNotFoundError(2, "No such file or directory", "seq/events.h5")

    monkeypatch.setattr(info, "run", vanished)
    assert main(["info", "seq"]) == 2
    _one_error_line(capsys.readouterr().err, "ti-cmax info: error: seq/events.h5: No such file or directory")
