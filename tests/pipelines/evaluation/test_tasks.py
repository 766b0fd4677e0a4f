"""The task model and its executors: Dask (LocalCluster, processes) matches the serial run, a rerun skips finished
tasks, a failing task or a dying worker is reported while the others finish."""
import json
import os
import sys
import time

import pytest

from ti_cmax.config import update_config
from ti_cmax.pipelines.evaluation import benchmark as B
from ti_cmax.pipelines.evaluation import tasks as T

TINY = {"benchmark.duration": 0.3, "backend.pano_height": 64, "benchmark.map_height": 64, "benchmark.ba_degrees": "",
        "frontend_cg_max_iters": 10}
FIGURES = ("abs_rmse_deg", "abs_max_deg", "ea_percent", "gm", "map_events", "status", "method")


def _figures(results):
    return [[{k: r[k] for k in FIGURES} for r in res["rows"]] for res in results]


@pytest.fixture(scope="module")
def tiny_cfg():
    return update_config(B.BenchmarkConfig(), TINY)


@pytest.mark.slow
def test_dask_local_cluster_matches_serial(tmp_path, tiny_cfg, ti_runtime):
    distributed = pytest.importorskip("distributed")
    spec = [B.SUITE["playroom"]]
    methods = ["cmax-omega", "imu"]
    # serial, single-threaded (this process's Taichi may run more threads: then in one spawned process)
    serial = B.run_benchmark(tiny_cfg, spec, methods, tmp_path / "serial", executor=T.LocalExecutor(1, threads=1),
                             plots=False)
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None,
                                  worker_class=distributed.Nanny) as cluster, distributed.Client(cluster) as client:
        executor = T.DaskExecutor(client=client, threads=1)
        remote = B.run_benchmark(tiny_cfg, spec, methods, tmp_path / "dask", executor=executor, plots=False)
        pids = {json.loads(p.read_text())["pid"] for p in (tmp_path / "dask" / "tasks").glob("*/result.json")}
    assert os.getpid() not in pids  # the tasks ran in the workers
    a, b = _figures(serial), _figures(remote)
    assert [r["method"] for r in a[0]] == ["ground truth", "CMax-omega", "IMU dead reckoning"]
    assert all(r["status"] == "ok" for r in a[0] + b[0])
    assert a == b  # single-threaded Taichi in both: the same numbers, bit for bit


def _tasks(tmp_path, cfg, broken=True):
    folder, _, _ = B.ensure_sequence(B.SUITE["playroom"], cfg.benchmark, tmp_path / "sequences")
    datasets = [("playroom", str(folder), {"sensor": "DVS128", "scene": "town"})]
    if broken:  # a dataset folder without events: its task fails (InputError), the others must not
        (tmp_path / "broken").mkdir(exist_ok=True)
        datasets.append(("broken", str(tmp_path / "broken"), {}))
    return B.suite_tasks(datasets, ["gt", "imu"], {"": cfg})


@pytest.mark.slow
def test_rerun_skips_finished_tasks_and_reports_failures(tmp_path, tiny_cfg, ti_runtime):
    out = tmp_path / "out"
    tasks = _tasks(tmp_path, tiny_cfg)
    first = T.run_tasks(tasks, out, T.LocalExecutor(1), quiet=True)
    status = {t.id: r["status"] for t, r in zip(tasks, first.results)}
    assert status == {"playroom-gt": "done", "playroom-imu": "done", "broken-gt": "failed", "broken-imu": "failed"}
    assert first.failed == 2 and not first.skipped
    failed = json.loads((out / "tasks" / "broken-imu" / "result.json").read_text())
    assert "InputError" in failed["error"] and "InputError" in (out / "tasks" / "broken-imu" / "task.log").read_text()
    done = out / "tasks" / "playroom-imu"
    assert (done / "trajectory_0.txt").is_file() and (done / "arrays.npz").is_file()
    assert not [p for p in (out / "tasks").iterdir() if p.name.startswith(T.TMP_PREFIX)]
    groups = B.group_results(tasks, first.results)
    broken_rows = [r for g in groups for r in g["rows"] if g["sequence"] == "broken"]
    assert [r["status"] for r in broken_rows] == ["failed", "failed"]
    assert "dataset" in broken_rows[1]["note"] or "events" in broken_rows[1]["note"]
    text = B.format_tables(groups, {"map_height": 64})
    assert "IMU dead reckoning on broken: failed, InputError" in text

    mtime = (done / "result.json").stat().st_mtime_ns
    second = T.run_tasks(tasks, out, T.LocalExecutor(1), quiet=True)
    assert second.skipped == {"playroom-gt", "playroom-imu"} and second.ran == 2  # the failed ones are retried
    assert (done / "result.json").stat().st_mtime_ns == mtime
    assert [r["rows"] for r in second.results[:2]] == [r["rows"] for r in first.results[:2]]

    # another config (its hash) or another dataset content (its fingerprint) is another task
    other = _tasks(tmp_path, update_config(tiny_cfg, {"benchmark.map_height": 32}), broken=False)
    third = T.run_tasks(other, out, T.LocalExecutor(1), quiet=True)
    assert not third.skipped and third.ran == 2
    assert T.dataset_fingerprint(tasks[0].dataset) == tasks[0].fingerprint
    (tmp_path / "broken" / "events.txt").write_text("0.1 1 1 1\n")
    assert T.dataset_fingerprint(tmp_path / "broken") != tasks[2].fingerprint


def _maybe_die(i):
    if i == 0:
        time.sleep(1.0)  # still running beside call 1 when its worker dies (and the pool with it)
    if i == 1:
        time.sleep(0.2)
        os._exit(3)  # a worker lost mid-task (crash, out of memory)
    return i * 10


@pytest.mark.slow
def test_local_pool_survives_a_dying_worker():
    """Only the call that kills its worker fails, also the one that ran beside it when the pool broke."""
    ex = T.LocalExecutor(jobs=2, threads=1)
    out = {i: (ok, v) for i, ok, v in ex.results(_maybe_die, [(0,), (1,), (2,), (3,)])}
    assert out[0] == (True, 0) and out[2] == (True, 20) and out[3] == (True, 30)
    assert out[1][0] is False and "worker process died" in out[1][1]


def test_config_hash_ignores_key_order():
    assert T.config_hash({"a": 1, "b": {"c": 2}}) == T.config_hash({"b": {"c": 2}, "a": 1})
    assert T.config_hash({"a": 1}) != T.config_hash({"a": 2})


@pytest.mark.slow
def test_batch_cli_parameter_sets_on_a_process_pool(tmp_path):
    from ti_cmax.cli import main

    suite = tmp_path / "suite.yaml"
    suite.write_text(
        "datasets:\n  tiny: {simulate: {sensor: DVS128, scene: town, duration: 0.3, seed: 4}}\n"
        "methods: [imu]\n"
        "config: {benchmark.map_height: 32, benchmark.ba_degrees: ''}\n"
        "parameters:\n  small: {}\n  large: {benchmark.map_height: 64}\n")
    out = tmp_path / "out"
    assert main(["batch", str(suite), "--out", str(out), "--jobs", "2", "--threads", "1", "--quiet", "--no-plots"]) == 0
    assert sorted(p.name for p in (out / "tasks").iterdir()) == [
        "large-tiny-gt", "large-tiny-imu", "small-tiny-gt", "small-tiny-imu"]
    import csv

    with open(out / "results.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert [(r["parameters"], r["method"]) for r in rows] == [
        ("small", "ground truth"), ("small", "IMU dead reckoning"), ("large", "ground truth"),
        ("large", "IMU dead reckoning")]
    assert rows[1]["abs_rmse_deg"] == rows[3]["abs_rmse_deg"]  # the map size does not change the trajectory
    assert rows[1]["ea_percent"] != rows[3]["ea_percent"]
    text = (out / "tables.md").read_text()
    assert "parameter set small" in text and "parameter set large" in text
    pids = {json.loads(p.read_text())["pid"] for p in (out / "tasks").glob("*/result.json")}
    assert os.getpid() not in pids

    bad = tmp_path / "bad.yaml"
    bad.write_text("datasets:\n  x: {simulate: {sensor: DVS128, nonsense: 1}}\nmethods: [imu]\n")
    assert main(["batch", str(bad), "--out", str(tmp_path / "bad_out"), "--quiet"]) == 2
    bad.write_text("datasets: {x: /nowhere}\n")
    assert main(["batch", str(bad), "--out", str(tmp_path / "bad_out"), "--quiet"]) == 2
    assert not (tmp_path / "bad_out").exists()


def test_tasks_line_counts_method_runs_that_ended_in_an_error():
    """A method that raises on one dataset is a row (status "error", its note in tables.md), not a failed task: the
    summary line says so instead of only "0 failed"."""
    from ti_cmax.commands.batch import tasks_line

    groups = [{"tasks": {"done": 2}, "rows": [{"status": "ok"}, {"status": "error", "note": "InputError: ..."}]}]
    assert "1 method run(s) ended in an error" in tasks_line(groups, 1.0)
    assert "error" not in tasks_line([{"tasks": {"done": 1}, "rows": [{"status": "lost"}]}], 1.0)


def test_suite_files_refuse_names_that_leave_the_output_folder_and_odd_method_lists(tmp_path):
    """A dataset name becomes file names (plots): 'a/../../ESCAPED' wrote outside --out; `methods: 5` was a
    TypeError."""
    from ti_cmax.commands.batch import load_suite
    from ti_cmax.errors import InputError

    (tmp_path / "d").mkdir()
    for text, message in (("datasets:\n  'a/../../ESCAPED': d\nmethods: [cmax-omega]\n", "must not be empty, hold"),
                          ("datasets:\n  d: d\nmethods: 5\n", "methods: expected a list")):
        suite = tmp_path / "suite.yaml"
        suite.write_text(text)
        with pytest.raises(InputError, match=message):
            load_suite(suite, {})


def test_batch_records_datasets_that_cannot_be_read_and_refuses_unreadable_files(tmp_path, capsys):
    """Found by fuzzing: with a dataset folder without events (or a corrupt file) every task of it failed, recorded
    as designed, but the plots (on by default) opened the dataset again: exit 2 after tasks/ was written, and no
    tables. A file that cannot be read at all (I/O error, permissions) was a traceback."""
    from ti_cmax.cli import main

    (tmp_path / "empty").mkdir()
    (tmp_path / "corrupt.h5").write_bytes(b"not an HDF5 file")
    suite = tmp_path / "suite.yaml"
    suite.write_text("datasets:\n  empty: empty\n  corrupt: corrupt.h5\nmethods: [imu]\n")
    out = tmp_path / "out"
    assert main(["batch", str(suite), "--out", str(out), "--quiet"]) == 1  # failed tasks: exit 1, their errors kept
    results = [json.loads(p.read_text()) for p in sorted((out / "tasks").glob("*/result.json"))]
    assert [(r["id"], r["status"]) for r in results] == [
        ("default-corrupt-gt", "failed"), ("default-corrupt-imu", "failed"), ("default-empty-gt", "failed"),
        ("default-empty-imu", "failed")]
    assert not [p for p in (out / "tasks").iterdir() if p.name.startswith(T.TMP_PREFIX)]
    tables = (out / "tables.md").read_text()
    assert "IMU dead reckoning on empty: failed, InputError" in tables and "no events found" in tables
    assert "cannot open as HDF5" in tables
    rows = json.loads((out / "results.json").read_text())["results"]
    assert {r["status"] for g in rows for r in g["rows"]} == {"failed"}
    assert (out / "results.csv").is_file() and (out / "config.yaml").is_file()
    capsys.readouterr()

    if os.path.isfile("/proc/self/mem"):  # exists, and every read of its first page is an I/O error
        suite.write_text("datasets:\n  mem: /proc/self/mem\nmethods: [imu]\n")
        assert main(["batch", str(suite), "--out", str(tmp_path / "out2"), "--quiet"]) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and "datasets.mem: /proc/self/mem: cannot read" in err, err
        assert not (tmp_path / "out2").exists()


@pytest.mark.slow
def test_unguarded_script_running_calls_in_a_pool_is_told_why(tmp_path):
    """A script that runs calls on a local pool at its top level: each spawned worker runs the script again and
    would start a pool itself. The calls fail with the reason (they failed as 'worker process died (crash or out of
    memory)', under multiprocessing's page of traceback from every worker)."""
    import subprocess

    script = tmp_path / "unguarded_pool.py"
    script.write_text("import math\n"
                      "from ti_cmax.pipelines.evaluation.tasks import LocalExecutor, run_calls\n"
                      "print(run_calls(LocalExecutor(jobs=2, threads=1), math.sqrt, [(4.0,), (9.0,)], quiet=True))\n")
    proc = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=120, cwd=tmp_path)
    assert proc.returncode == 0
    assert proc.stdout.count('if __name__ == "__main__":') == 2, proc.stdout
    assert "bootstrapping phase" not in proc.stderr
