"""The figure process (ti_cmax/figure_process.py): `slam`'s run.png and map.png drawn in a forked process, the same
files as drawn in the command's own process, errors raised in the command, a lost process replaced."""
import os
import subprocess
import sys

import pytest

FORKS = sys.platform.startswith("linux") and len(os.sched_getaffinity(0)) >= 2

RESULT = """
import json, os, sys
from pathlib import Path

def probe(path):
    with open(path, "w") as fh:
        json.dump({"pid": os.getpid(), "engine": "taichi" in sys.modules or "quadrants" in sys.modules}, fh)

from ti_cmax.figure_process import FigureProcess
figures = FigureProcess.start()  # before the back-end's modules (and the engine) are imported here

import numpy as np
from ti_cmax.commands.slam import write_result
from ti_cmax.config import SlamConfig
from ti_cmax.pipelines.backend import WindowReport
from ti_cmax.pipelines.frontend import FrontendResult
from ti_cmax.pipelines.slam import SlamResult
from ti_cmax.trajectory import Trajectory
from ti_cmax import so3

t = np.linspace(0.0, 1.0, 50)
traj = Trajectory(t, so3.exp(np.outer(t, [0.1, 0.2, 0.3])))
gt = Trajectory(t, so3.exp(np.outer(t, [0.1, 0.21, 0.3])))
rng = np.random.default_rng(3)
pano = np.zeros((64, 128), np.float32)
pano[20:40, 30:90] = rng.poisson(2.0, (20, 60))
windows = [WindowReport(0.0, 0.5, 100, True, 1.0, max_correction=0.01),
           WindowReport(0.25, 0.75, 100, False, 1.0, rejected=True)]
result = SlamResult(None, traj, pano, {"status": "ok", "method": "cmax-slam"}, None, windows)
"""


def _python(code: str, *args) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", code, *map(str, args)], capture_output=True, text=True, timeout=300)


@pytest.mark.skipif(not FORKS, reason="the figure process is forked on Linux with 2 or more cores")
def test_the_figures_are_drawn_in_the_figure_process_and_are_the_same_files(tmp_path):
    code = RESULT + """
forked, here = Path(sys.argv[1]), Path(sys.argv[2])
forked.mkdir(); here.mkdir()
with figures:
    report = write_result(forked, result, SlamConfig(), groundtruth=gt, figures=figures)
    figures.submit(probe, forked / "probe.json")
    figures.wait()
    print(figures.forked, "matplotlib" in sys.modules, sorted(report["figure_process"]))
write_result(here, result, SlamConfig(), groundtruth=gt)
probe(here / "probe.json")
"""
    proc = _python(code, tmp_path / "forked", tmp_path / "here")
    assert proc.returncode == 0, proc.stderr
    # forked; this process drew nothing (no matplotlib until the second, in-process write); the process's figures
    assert proc.stdout.split() == ["True", "False", "['cpu_seconds',", "'peak_rss_mb']"]
    import json

    forked, here = (json.loads((tmp_path / d / "probe.json").read_text()) for d in ("forked", "here"))
    assert forked["pid"] != here["pid"] and not forked["engine"]  # the windows unpickled without the engine
    for name in ("run.png", "map.png", "map.npy", "trajectory.txt", "config.yaml"):
        assert (tmp_path / "forked" / name).read_bytes() == (tmp_path / "here" / name).read_bytes(), name
    assert not [p.name for p in (tmp_path / "forked").iterdir() if p.name.startswith(".")]  # no temp file left


@pytest.mark.skipif(not FORKS, reason="the figure process is forked on Linux with 2 or more cores")
def test_an_error_of_the_figure_process_is_raised_in_the_command_and_a_lost_process_is_replaced(tmp_path):
    code = """
import os, signal, sys
from pathlib import Path
from ti_cmax.figure_process import FigureProcess  # first: numpy's BLAS threads start unless ti_cmax limits them
from ti_cmax.commands.slam import write_png
import numpy as np

with FigureProcess.start() as figures:
    figures.submit(write_png, Path(sys.argv[1]) / "missing" / "map.png", np.zeros((4, 4), np.uint8))
    try:
        figures.wait()
    except OSError as exc:
        print(type(exc).__name__, figures.forked)
with FigureProcess.start() as figures:
    pid = figures._process.pid
    os.kill(pid, signal.SIGKILL)
    os.waitpid(pid, 0)
    figures.submit(write_png, Path(sys.argv[1]) / "map.png", np.zeros((4, 4), np.uint8))
    figures.wait()
    print(figures.forked, os.path.getsize(Path(sys.argv[1]) / "map.png") > 0)
"""
    proc = _python(code, tmp_path)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.split() == ["FileNotFoundError", "False", "False", "True"]


def test_without_fork_the_jobs_run_here(tmp_path):
    """A process with another thread running forks nothing (a fork copies the locks other threads hold); nor one
    where TI_CMAX_FIGURE_PROCESS=0."""
    code = ("from ti_cmax.figure_process import FigureProcess\n"
            "with FigureProcess.start() as figures:\n"
            "    print(figures.forked)\n")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60,
                          env={**os.environ, "TI_CMAX_FIGURE_PROCESS": "0"})
    assert proc.stdout.split() == ["False"], proc.stderr
    code = """
import sys, threading, time
import numpy as np
from pathlib import Path
from ti_cmax.commands.slam import write_png
from ti_cmax.figure_process import FigureProcess

t = threading.Thread(target=time.sleep, args=(0.5,)); t.start()
with FigureProcess.start() as figures:
    figures.submit(write_png, Path(sys.argv[1]) / "map.png", np.zeros((4, 4), np.uint8))
    print(figures.forked, (Path(sys.argv[1]) / "map.png").exists(), figures.wait())
t.join()
"""
    proc = _python(code, tmp_path)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.split() == ["False", "True", "{}"]
