"""The whole process of a command beside its results: how the back-end worker starts, the offline cache every
process writes, the quick exit of the command line, the outputs' imports in a thread, and the timeline that
report.json keeps of it all (pipelines/evaluation/bench_process.py reads it)."""
import json
import os
import subprocess
import sys

import pytest

LINUX = sys.platform.startswith("linux")


def _python(code: str, env: dict | None = None) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300,
                          env={**os.environ, **(env or {})})


def test_a_slam_process_imports_neither_scipy_nor_matplotlib_before_its_outputs():
    """What `slam` imports before its first event (and its worker inherits): scipy (the joint refinement's L-BFGS,
    the trajectory's Rotation) only when a run needs it, matplotlib only for the figure."""
    code = ("import sys\n"
            "import ti_cmax.cli, ti_cmax.commands.slam, ti_cmax.io, ti_cmax.pipelines.slam, ti_cmax.pipelines.worker\n"
            "print(sorted({m.split('.')[0] for m in sys.modules} & {'scipy', 'matplotlib', 'PIL', 'imageio'}))\n")
    proc = _python(code)
    assert proc.stdout.split() == ["[]"], proc.stderr


def test_the_engine_import_leaves_out_its_version_check_and_dill_until_used():
    """Taichi's version check (off: urllib, http, ssl) and dill (interactive-shell sources) are not imported with
    it; dill is there on first use, for Taichi and for anyone else; hdf5plugin only for a file that needs it."""
    code = ("import sys\n"
            "import ti_cmax.cli, ti_cmax.commands.slam, ti_cmax.io, ti_cmax.pipelines.slam\n"
            "from ti_cmax.kernels import runtime\n"
            "print(sorted({'urllib.request', 'http.client', 'ssl', 'dill', 'hdf5plugin'} & set(sys.modules)))\n"
            "if runtime.ENGINE == 'taichi':\n"
            "    from taichi.lang import _wrap_inspect\n"
            "    import dill\n"
            "    assert _wrap_inspect.dill.source is dill.source\n"
            "runtime.ensure_init()\n"
            "print('initialized')\n")
    proc = _python(code)
    assert proc.stdout.split() == ["[]", "initialized"], proc.stderr


def test_kernels_in_a_class_body_and_at_module_level_are_told_apart_as_taichi_does(tmp_path):
    """runtime._patch_class_check answers Taichi's "is this decorator in a class body?" from the frame's source line
    without inspect's scan of every module: a data-oriented class's kernel takes its instance, a module's does not."""
    script = tmp_path / "kernels_here.py"
    script.write_text(
        "import numpy as np\n"
        "from ti_cmax.kernels.runtime import ensure_init, ti\n"
        "import taichi.lang.kernel_impl as kernel_impl\n"
        "\n"
        "@ti.data_oriented\n"
        "class Scaled:\n"
        "    def __init__(self, k):\n"
        "        self.k = k\n"
        "\n"
        "    @ti.kernel\n"
        "    def apply(self, a: ti.types.ndarray(dtype=ti.f64, ndim=1)):\n"
        "        for i in a:\n"
        "            a[i] *= self.k\n"
        "\n"
        "@ti.kernel\n"
        "def double(a: ti.types.ndarray(dtype=ti.f64, ndim=1)):\n"
        "    for i in a:\n"
        "        a[i] *= 2\n"
        "\n"
        "ensure_init()\n"
        "a = np.ones(4)\n"
        "Scaled(3.0).apply(a)\n"
        "double(a)\n"
        "print(a.tolist(), kernel_impl._inside_class.__module__)\n")
    proc = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    from ti_cmax.kernels.runtime import ENGINE

    assert proc.stdout.split() == ["[6.0,", "6.0,", "6.0,", "6.0]",
                                   "ti_cmax.kernels.runtime" if ENGINE == "taichi" else "quadrants.lang.kernel_impl"]


@pytest.mark.skipif(not LINUX, reason="the worker is forked on Linux only")
def test_the_worker_is_forked_from_a_single_threaded_process_before_the_engine_starts():
    """Forked, the worker inherits the imports (about 0.4 CPU s that a spawned one repeats before its kernels);
    with another thread running, or after the engine's init (a forked worker would hang), it is spawned."""
    code = ("import threading, time\n"
            "from ti_cmax.pipelines.worker import worker_start_method\n"
            "from ti_cmax.kernels import runtime\n"
            "print(worker_start_method())\n"
            "t = threading.Thread(target=time.sleep, args=(0.5,)); t.start()\n"
            "print(worker_start_method()); t.join()\n"
            "runtime.ensure_init()\n"
            "print(worker_start_method())\n")
    proc = _python(code)
    assert proc.stdout.split() == ["fork", "spawn", "spawn"], proc.stderr


@pytest.mark.skipif(not LINUX, reason="the worker is forked on Linux only")
def test_a_forked_worker_hands_the_final_map_over_in_shared_memory():
    """SharedMap: what the worker puts there the main process reads (no 8 MB result message); a map of another
    shape or type is not put (it goes in the message, as from a spawned worker)."""
    import multiprocessing as mp

    import numpy as np

    from ti_cmax.config import SlamConfig, load_config
    from ti_cmax.pipelines.worker import SharedMap

    shared = SharedMap.create(load_config(SlamConfig, None, ["pano_height=64"]))
    assert shared.shape == (64, 128)
    image = np.arange(64 * 128, dtype=np.float32).reshape(64, 128)
    child = mp.get_context("fork").Process(target=shared.put, args=(image,))
    child.start()
    child.join()
    assert child.exitcode == 0 and np.array_equal(shared.array(), image)
    assert not shared.put(image.astype(np.float64)) and not shared.put(image[:32])


def test_progress_bars_start_no_thread():
    """tqdm's monitor thread would make every `slam` spawn its worker instead of forking it."""
    code = ("import threading\n"
            "from ti_cmax import progress\n"
            "progress.set_quiet(False)\n"
            "with progress.stage('x'):\n"
            "    bar = progress.progress(total=3.0, desc='y', unit='s'); bar.update(1.0)\n"
            "    print(threading.active_count())\n")
    proc = _python(code)
    assert proc.stdout.split() == ["1"], proc.stderr


def test_the_command_line_ends_at_once_after_its_exit_hooks():
    """entry_point (the ti-cmax script) skips the interpreter's teardown but runs the atexit hooks, flushes the
    output and keeps the exit code."""
    hook = "import atexit; atexit.register(lambda: print('hook ran'))\n"
    proc = _python(hook + "import sys; sys.argv = ['ti-cmax', 'params', 'slam']\n"
                          "from ti_cmax.cli import entry_point; entry_point()\n")
    assert proc.returncode == 0 and "num_events_per_packet" in proc.stdout
    assert proc.stdout.rstrip().endswith("hook ran")
    proc = _python(hook + "import sys; sys.argv = ['ti-cmax', 'info', '/nonexistent/folder']\n"
                          "from ti_cmax.cli import entry_point; entry_point()\n")
    assert proc.returncode == 2 and proc.stderr.startswith("ti-cmax info: error") and "hook ran" in proc.stdout


def test_the_output_preload_imports_the_figure_modules_in_a_thread():
    code = ("import sys, threading\n"
            "from ti_cmax.commands.slam import OutputPreload\n"
            "before = 'matplotlib.figure' in sys.modules\n"
            "preload = OutputPreload(); preload.start()\n"
            "names = [t.name for t in threading.enumerate()]\n"
            "preload.join()\n"
            "print(before, 'ti-cmax-output-preload' in names, all(m in sys.modules for m in OutputPreload.MODULES))\n")
    proc = _python(code)
    assert proc.stdout.split() == ["False", "True", "True"], proc.stderr


def test_on_start_runs_once_before_the_first_event(short_sequence):
    from ti_cmax.config import SlamConfig
    from ti_cmax.pipelines.slam import run_slam

    packets, started = [], []

    class Watch:
        def on_packet(self, packet, omega):
            packets.append(packet.t_ref)

        def attach(self, online):
            pass

    ev = short_sequence.events
    run_slam(ev[:len(ev) // 4], short_sequence.camera, SlamConfig(), observer=Watch(),
             on_start=lambda: started.append(len(packets)))
    assert started == [0] and packets


@pytest.mark.slow
def test_every_process_of_a_run_writes_its_kernels_to_the_offline_cache_and_the_timeline(tmp_path):
    """A back-end worker ends without the interpreter's teardown, where the engine writes its offline cache: it
    compiled its kernels again in every run. Now a run with a worker leaves the same kernels in a new cache as one
    in a single process. report.json's timeline: the main process's points in order, the worker's apart."""
    from ti_cmax.simulate import SimulatorConfig, simulate_sequence, write_sequence

    seq = write_sequence(simulate_sequence(SimulatorConfig(scene="town", duration=0.3, seed=4)), tmp_path / "seq",
                         events_format="h5")
    cached, reports = {}, {}
    for mode in ("--parallel", "--sequential"):
        cache, out = tmp_path / f"cache{mode}", tmp_path / f"out{mode}"
        proc = subprocess.run([sys.executable, "-m", "ti_cmax.cli", "slam", str(seq), "--out", str(out), "--quiet",
                               "--threads", "1", "--set", "pano_height=128", mode], capture_output=True, text=True,
                              timeout=600, env={**os.environ, "TI_OFFLINE_CACHE_FILE_PATH": str(cache)})
        assert proc.returncode == 0, proc.stderr
        cached[mode] = {p.name for p in cache.rglob("*.tic")}
        reports[mode] = json.loads((out / "report.json").read_text())
    assert cached["--parallel"] == cached["--sequential"] and len(cached["--parallel"]) > 2

    forks = LINUX and len(os.sched_getaffinity(0)) >= 2  # run.png and map.png drawn in a figure process
    for mode, report in reports.items():
        assert ("figure_process" in report) == forks
        points = report["timeline_seconds"]
        assert list(points) == ["command", "imported", "ready", "frontend_done", "closed", "outputs"]
        walls = [wall for wall, _ in points.values()]
        assert walls == sorted(walls) and walls[-1] - walls[0] < report["wall_seconds"] + 60
    worker = reports["--parallel"]["backend_process"]
    assert list(worker["timeline_seconds"]) == ["started", "ready", "done"]
    assert worker["start_method"] == ("fork" if LINUX else "spawn")
    assert worker["process_cpu_seconds"] >= worker["timeline_seconds"]["done"][1] > 0
    assert "backend_process" not in reports["--sequential"]
