"""Output files get the mode the umask gives: the atomic temp-file-and-rename writer must not
leave mkstemp's 0600 on them."""
import os
import stat

import pytest

from ti_cmax.cli import main
from ti_cmax.outputs import atomic_path


@pytest.fixture
def umask():
    old = os.umask(0o022)
    yield lambda mask: os.umask(mask)
    os.umask(old)


@pytest.mark.parametrize("mask, mode", [(0o022, 0o644), (0o027, 0o640), (0o077, 0o600)])
def test_atomic_path_respects_umask(tmp_path, umask, mask, mode):
    umask(mask)
    target = tmp_path / "sub" / "out.txt"
    with atomic_path(target) as tmp:
        tmp.write_text("x")
    assert stat.S_IMODE(target.stat().st_mode) == mode


def test_atomic_path_removes_the_folders_it_made_when_the_block_fails(tmp_path):
    """Ctrl-C while `map --out new/m.png` wrote its PNG left the folder new/ behind (empty)."""
    (tmp_path / "kept").mkdir()
    for target in (tmp_path / "new" / "sub" / "m.png", tmp_path / "kept" / "m.png"):
        with pytest.raises(KeyboardInterrupt):
            with atomic_path(target) as tmp:
                tmp.write_bytes(b"partial")
                raise KeyboardInterrupt
    assert sorted(p.name for p in tmp_path.iterdir()) == ["kept"] and not any((tmp_path / "kept").iterdir())


def test_command_outputs_respect_umask(tmp_path, umask, capsys):
    from ti_cmax.camera import Camera
    from ti_cmax.io import write_calib_txt

    umask(0o022)
    d = tmp_path / "seq"
    d.mkdir()
    (d / "events.txt").write_text("".join(f"{0.001 * i:.6f} {i % 240} {i % 180} {i % 2}\n" for i in range(1, 50)))
    write_calib_txt(d / "calib.txt", Camera(240, 180, 199.0, 199.0, 120.0, 90.0))
    gt = tmp_path / "gt.txt"
    gt.write_text("".join(f"{0.1 * i:.1f} 0 0 0 0 0 0 1\n" for i in range(30)))
    assert main(["convert", str(d), str(tmp_path / "ev.h5"), "--quiet"]) == 0
    assert main(["evaluate", "--groundtruth", str(gt), "--estimate", str(gt), "--out", str(tmp_path / "e.json")]) == 0
    for name in ("ev.h5", "e.json"):
        assert stat.S_IMODE((tmp_path / name).stat().st_mode) == 0o644, name


def test_json_ready_makes_strict_json():
    """Every report.json is strict JSON: NaN (an error over a sequence shorter than its window) was written as NaN."""
    import json

    import numpy as np

    from ti_cmax.outputs import json_ready

    doc = json_ready({"a": float("nan"), "b": [np.float32(1.5), np.inf], "c": np.int64(3), "d": np.array([1.0, np.nan]),
                      "e": np.bool_(True)})
    assert json.loads(json.dumps(doc, allow_nan=False)) == {"a": None, "b": [1.5, None], "c": 3, "d": [1.0, None],
                                                            "e": True}


def test_ctrl_c_during_start_up_is_the_one_line_interruption(monkeypatch, capsys):
    """Found by fuzzing: Ctrl-C while the parser imported the command modules (or Taichi's C++ module turned it into
    ImportError "initialization failed") printed a traceback instead of the line and exit code of a later Ctrl-C."""
    import signal

    from ti_cmax import cli

    def interrupted(command=None):
        raise KeyboardInterrupt

    def run():
        try:
            return main(["slam", "seq", "--out", "out"])
        except (KeyboardInterrupt, ImportError) as exc:  # a KeyboardInterrupt would end the test session
            pytest.fail(f"main() raised {type(exc).__name__}")

    monkeypatch.setattr(cli, "build_parser", interrupted)
    assert run() == 130
    assert capsys.readouterr().err == "ti-cmax slam: interrupted\n"

    def converted(command=None):
        try:
            os.kill(os.getpid(), signal.SIGINT)  # the command line's handler raises KeyboardInterrupt here
            for _ in range(1000):
                pass
        except KeyboardInterrupt:
            raise ImportError("initialization failed") from None

    monkeypatch.setattr(cli, "build_parser", converted)
    assert run() == 130
    assert capsys.readouterr().err == "ti-cmax slam: interrupted\n"


def test_a_ctrl_c_swallowed_by_a_bare_except_still_ends_the_command_before_it_writes(tmp_path, monkeypatch, capsys):
    """Found by fuzzing: Ctrl-C ~1 s into `slam` landed in Taichi's kernel decorator, whose bare ``except:`` swallowed
    the KeyboardInterrupt: the run went on and ended with exit 0 and every output written."""
    import signal

    from ti_cmax.commands import evaluate

    run = evaluate.run

    def swallowing(args):
        try:
            os.kill(os.getpid(), signal.SIGINT)
            for _ in range(1000):
                pass
        except:  # noqa: E722 - as taichi.lang.kernel_impl._inside_class
            pass
        return run(args)

    gt = tmp_path / "gt.txt"
    gt.write_text("".join(f"{0.1 * i:.1f} 0 0 0 0 0 0 1\n" for i in range(30)))
    monkeypatch.setattr(evaluate, "run", swallowing)
    assert main(["evaluate", "--groundtruth", str(gt), "--estimate", str(gt), "--out", str(tmp_path / "e.json")]) == 130
    assert capsys.readouterr().err.endswith("ti-cmax evaluate: interrupted\n")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["gt.txt"]
    monkeypatch.setattr(evaluate, "run", run)  # the next command starts afresh
    assert main(["evaluate", "--groundtruth", str(gt), "--estimate", str(gt), "--out", str(tmp_path / "e.json")]) == 0


def test_the_command_line_imports_nothing_heavy_before_its_ctrl_c_handling():
    """The console script imports ti_cmax.cli (and the package) before main() can map Ctrl-C: that window held
    numpy's import (0.25 s of every start-up), where Ctrl-C printed a traceback."""
    import subprocess
    import sys

    code = "import sys, ti_cmax.cli; print([m for m in ('numpy', 'yaml', 'scipy') if m in sys.modules])"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0 and out.stdout.strip() == "[]", out.stdout + out.stderr


def test_a_second_ctrl_c_does_not_cut_the_cleanup_of_the_first_short(tmp_path, monkeypatch, capsys):
    """A terminal's repeated Ctrl-C (or `timeout -s INT`, which signals the process and then its group): raised during
    the first one's cleanup it left the output folder behind, and during the interpreter's exit it printed a
    traceback from multiprocessing's exit handler; ignored once the command is ending."""
    import signal
    import sys

    from ti_cmax import outputs
    from ti_cmax.commands import params

    out = tmp_path / "out"

    def ctrl_c():
        os.kill(os.getpid(), signal.SIGINT)
        for _ in range(1000):
            pass

    def run(args):
        with outputs.OutputDir(out) as d:
            (d / "a.txt").write_text("x")
            ctrl_c()
        return 0

    rmtree = outputs.shutil.rmtree

    def slow_rmtree(*a, **kw):
        ctrl_c()  # the second Ctrl-C, in the middle of the first one's cleanup
        return rmtree(*a, **kw)

    monkeypatch.setattr(params, "run", run)
    monkeypatch.setattr(outputs.shutil, "rmtree", slow_rmtree)
    monkeypatch.setattr(sys, "argv", ["ti-cmax", "params"])
    before = signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)
    try:
        assert main() == 130  # argv None: the process's own command line
        ignored = signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)
    finally:
        signal.signal(signal.SIGINT, before[0])
        signal.signal(signal.SIGTERM, before[1])
    assert capsys.readouterr().err == "ti-cmax params: interrupted\n"
    assert not out.exists()
    assert ignored == (signal.SIG_IGN, signal.SIG_IGN)  # until the process exits
    assert main(["params"]) == 130 and signal.getsignal(signal.SIGINT) == before[0]  # in-process: restored


@pytest.mark.skipif(not hasattr(os, "fork"), reason="needs fork")
def test_an_output_lock_ends_with_its_release_also_while_a_forked_child_holds_the_folder_open(tmp_path):
    """A forked back-end worker inherits the lock's descriptor: the lock still ends when the run releases it."""
    import signal

    from ti_cmax.errors import OutputError
    from ti_cmax.outputs import OutputLock

    first = OutputLock(tmp_path / "out")
    first.acquire()
    child = os.fork()
    if child == 0:  # holds its copy of the descriptor until killed
        signal.pause()
        os._exit(0)
    try:
        with pytest.raises(OutputError, match="another ti-cmax run"):
            OutputLock(tmp_path / "out").acquire()
        first.release(remove=False)
        second = OutputLock(tmp_path / "out")
        second.acquire()
        second.release(remove=False)
    finally:
        os.kill(child, signal.SIGKILL)
        os.waitpid(child, 0)
