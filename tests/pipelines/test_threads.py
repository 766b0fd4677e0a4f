"""Reproducibility: float atomics make results depend on the thread count, but one thread
(--threads 1, or --set num_threads=1) gives the same bytes run after run. Runs in subprocesses: the thread count
is fixed when Taichi starts."""
import ast
import os
import subprocess
import sys

import numpy as np
import pytest

pytestmark = pytest.mark.slow


def _slam(seq, out, *threads):
    cmd = [sys.executable, "-m", "ti_cmax.cli", "slam", str(seq), "--out", str(out), "--quiet",
           "--set", "pano_height=128", *threads]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    return {name: (out / name).read_bytes() for name in ("trajectory.txt", "angular_velocity.txt", "map.npy")}


def test_one_thread_is_bit_exact(tmp_path):
    from ti_cmax.simulate import SimulatorConfig, simulate_sequence, write_sequence

    seq = write_sequence(simulate_sequence(SimulatorConfig(scene="town", sensor="DVS128", duration=0.25, seed=2)),
                         tmp_path / "seq", events_format="h5")
    first = _slam(seq, tmp_path / "a", "--threads", "1")
    second = _slam(seq, tmp_path / "b", "--set", "num_threads=1")  # the config key reaches the runtime too
    assert first == second


def test_a_worker_process_halves_the_default_thread_count(monkeypatch):
    """With a back-end worker beside it (--parallel) each process takes half the cores; a chosen count is kept."""
    from ti_cmax.kernels import runtime

    monkeypatch.delenv("TI_CMAX_THREADS", raising=False)
    monkeypatch.setattr(runtime, "_state", {"initialized": False, "threads": None})
    monkeypatch.setattr(runtime, "available_cores", lambda: 8)
    runtime.share_cores(2)
    assert runtime.num_threads() == 4
    monkeypatch.setattr(runtime, "_state", {"initialized": False, "threads": 3})
    runtime.share_cores(2)
    assert runtime.num_threads() == 3
    monkeypatch.setattr(runtime, "_state", {"initialized": False, "threads": None})
    monkeypatch.setenv("TI_CMAX_THREADS", "2")
    runtime.share_cores(2)
    assert runtime.num_threads() == 2


_FRONTEND_OMEGA = """
import sys
import numpy as np
from ti_cmax.io import open_dataset
from ti_cmax.pipelines.frontend import estimate_angular_velocity
ds = open_dataset(sys.argv[1])
np.save(sys.argv[2], estimate_angular_velocity(ds.read_events(), ds.camera).omega)
"""


def test_front_end_output_does_not_depend_on_the_thread_count(tmp_path, monkeypatch):
    """The front-end's event loops run on the calling thread whatever the thread count (kernels/iwe.py
    IWEWorkspace: a thread-pool hand-off per loop cost more than a second thread saved), so its angular velocity
    is the same bytes with 1 and 2 threads (with parallel parts the sums were split and rounded differently)."""
    from ti_cmax.simulate import SimulatorConfig, simulate_sequence, write_sequence

    seq = write_sequence(simulate_sequence(SimulatorConfig(scene="city", duration=0.3, seed=4)),
                         tmp_path / "seq", events_format="h5")
    omegas = []
    for threads in ("1", "2"):
        monkeypatch.setenv("TI_CMAX_THREADS", threads)
        out = tmp_path / f"omega{threads}.npy"
        proc = subprocess.run([sys.executable, "-c", _FRONTEND_OMEGA, str(seq), str(out)], capture_output=True,
                              text=True, timeout=300)
        assert proc.returncode == 0, proc.stderr
        omegas.append(np.load(out))
    assert len(omegas[0]) > 10 and np.abs(omegas[0]).max() > 0.1
    assert omegas[0].tobytes() == omegas[1].tobytes()


def test_a_kernel_process_runs_blas_on_one_thread():
    """A process running the kernels keeps numpy's BLAS to one thread (its idle threads spin beside the kernels
    after each small product), unless OPENBLAS_NUM_THREADS was set; the variable reaches later processes."""
    code = ("import os, numpy, threadpoolctl\n"
            "from ti_cmax.kernels import runtime\n"
            "runtime.ensure_init()\n"
            "blas = [i['num_threads'] for i in threadpoolctl.threadpool_info() if i['user_api'] == 'blas']\n"
            "print(os.environ.get('OPENBLAS_NUM_THREADS'), blas)\n")
    env = {k: v for k, v in os.environ.items() if k != "OPENBLAS_NUM_THREADS"}
    env["TI_CMAX_THREADS"] = "2"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, env=env)
    assert out.returncode == 0, out.stderr
    value, blas = out.stdout.strip().splitlines()[-1].split(" ", 1)
    assert value == "1" and ast.literal_eval(blas) and set(ast.literal_eval(blas)) == {1}
    # ti_cmax imported before numpy: BLAS read the variable when it loaded, no threadpoolctl needed at the start
    first = ("import sys, ti_cmax\n" + code.replace("threadpoolctl\n", "sys\n")
             .replace("runtime.ensure_init()\n", "runtime.ensure_init(); print('threadpoolctl' in sys.modules)\n"
                      "import threadpoolctl\n"))
    out = subprocess.run([sys.executable, "-c", first], capture_output=True, text=True, timeout=120, env=env)
    loaded, line = out.stdout.strip().splitlines()[-2:]
    assert loaded == "False" and line.startswith("1 [") and set(ast.literal_eval(line[2:])) == {1}, out.stderr
    env["OPENBLAS_NUM_THREADS"] = "2"  # the user's choice is kept
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, env=env)
    assert out.stdout.strip().splitlines()[-1].startswith("2 [2")
