"""Tasks and executors behind ``ti-cmax benchmark``, ``sweep`` and ``batch``.

A :class:`Task` is one method on one dataset with one config, as plain data (picklable, shipped to any process or
machine). :func:`run_task` runs it and writes ``DIR/tasks/<id>/`` all at once (a temporary folder renamed into
place): ``result.json`` (identity, status, scored rows), ``task.log``, one TUM trajectory per row and
``arrays.npz`` (errors, aligned trajectories, maps: what the plots need). The tables are built from these files.

:func:`run_tasks` skips a task whose ``result.json`` says "done" for the same identity (dataset fingerprint,
method, config hash), runs the others on an executor with one progress bar over tasks (done / running / failed),
and records a failure (the task's exception, or a lost worker) as a result with status "failed": the other tasks
go on, and a rerun retries it. Executors:

* :class:`LocalExecutor`: one job runs in this process; more run in a ``spawn`` process pool (a process forked
  after ``ti.init`` hangs), each worker initializing Taichi with its own thread count.
* :class:`DaskExecutor`: a dask.distributed scheduler (``pip install ti-cmax[distributed]``). Workers must see
  the dataset paths and the output folder (a shared file system). Start them with ``--nthreads 1`` and as many
  ``--nworkers`` as wanted: tasks within one worker process are serialized (one Taichi runtime per process).

Ctrl-C: the local pool's workers are stopped and their temporary folders removed; finished tasks stay (complete
results, skipped by the next run). With Dask, tasks already running on workers finish and write their results.
"""
from __future__ import annotations

import contextlib
import hashlib
import json
import os
import shutil
import sys
import tempfile
import threading
import time
import traceback
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ti_cmax import progress
from ti_cmax.config import build_config
from ti_cmax.errors import UNGUARDED_MAIN, UNGUARDED_MAIN_EXIT, InputError, exit_if_spawn_bootstrapping
from ti_cmax.io import write_tum
from ti_cmax.kernels import runtime
from ti_cmax.outputs import json_ready, peak_rss_mb

from ti_cmax.pipelines.evaluation.methods import BenchmarkConfig, run_method

TASKS_DIR = "tasks"
TMP_PREFIX = ".tmp-"
_PROCESS_LOCK = threading.Lock()  # one task at a time per process (one Taichi runtime)


# ------------------------------------------------------------------------------------------------------------
# identity
# ------------------------------------------------------------------------------------------------------------

def config_hash(config: dict) -> str:
    """Hash of a config as a dict (``config_to_dict``): key order and YAML vs. --set origin do not matter."""
    text = json.dumps(config, sort_keys=True, default=str, separators=(",", ":"))
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def dataset_fingerprint(path, sample_bytes: int = 1 << 20) -> str:
    """Fingerprint of a dataset folder or file: per file its name, size and the bytes of its first, middle and
    last ``sample_bytes`` (a re-simulated or replaced recording changes it; reading all of a 5 GB file would not
    be worth it on every run). Paths and modification times are left out, so a copy keeps its fingerprint."""
    path = Path(path)
    if not path.exists():
        raise InputError("dataset not found", source=str(path))
    if not (path.is_dir() or path.is_file()):  # a FIFO or device: reading it could block or never end
        raise InputError("not a file or folder", source=str(path))
    h = hashlib.sha256()
    f = path
    try:  # a file that cannot be read (permissions, I/O error): one clear error naming it, not a traceback
        files = sorted(p for p in path.rglob("*") if p.is_file()) if path.is_dir() else [path]
        for f in files:
            size = f.stat().st_size
            h.update(f"{f.relative_to(path) if path.is_dir() else f.name}\0{size}\0".encode())
            with open(f, "rb") as fh:
                for offset in sorted({0, max(0, size // 2 - sample_bytes // 2), max(0, size - sample_bytes)}):
                    fh.seek(offset)
                    h.update(fh.read(sample_bytes))
    except OSError as exc:
        raise InputError(f"cannot read: {exc.strerror or exc}", source=str(f)) from None
    return h.hexdigest()[:16]


@dataclass(frozen=True)
class Task:
    """One method on one dataset with one config. ``labels`` (dataset name, sensor, parameter set, ...) are copied
    into every row of the result; they are not part of the identity."""

    id: str  # folder name under DIR/tasks
    method: str  # a key of pipelines.benchmark (METHOD_KEYS, "gt")
    dataset: str  # path the workers can read
    fingerprint: str
    config: dict  # config_to_dict of a BenchmarkConfig
    labels: dict = field(default_factory=dict)

    @property
    def config_hash(self) -> str:
        return config_hash(self.config)

    def identity(self) -> dict:
        return {"dataset_fingerprint": self.fingerprint, "method": self.method, "config_hash": self.config_hash}


def task_id(*parts: str) -> str:
    """Filesystem-safe folder name from its parts."""
    text = "-".join(p for p in parts if p)
    return "".join(c if c.isalnum() or c in "._+=-" else "_" for c in text)


# ------------------------------------------------------------------------------------------------------------
# running one task (in any process)
# ------------------------------------------------------------------------------------------------------------

def setup_process(threads: int | None) -> None:
    """Per worker process: Taichi's thread count (before its first kernel) and no progress bars."""
    progress.set_quiet(True)
    if threads and not runtime._state["initialized"]:
        runtime.set_num_threads(int(threads))


def call_in_worker(fn, args: tuple, threads: int | None = None):
    """What executors run: setup of the process, then ``fn(*args)``, one at a time per process."""
    with _PROCESS_LOCK:
        setup_process(threads)
        return fn(*args)


def _replace_dir(tmp: Path, final: Path) -> None:
    """Move a finished temporary folder onto ``final`` (a reader sees the old folder, none, or the new one)."""
    old = None
    if final.exists():
        old = final.parent / f"{TMP_PREFIX}old-{final.name}-{os.getpid()}"
        os.replace(final, old)
    os.replace(tmp, final)
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)


def _write_json(path: Path, doc: dict) -> dict:
    """Write ``doc`` as strict JSON; returns what a reader of the file gets (NaN -> None, numpy -> Python)."""
    doc = json_ready(doc)
    path.write_text(json.dumps(doc, indent=2) + "\n")
    return doc


@contextlib.contextmanager
def _task_folder(task: Task, out_dir):
    """A temporary folder for the task's files, moved onto DIR/tasks/<id> when the block ends; removed if the
    block raises or is interrupted."""
    tasks_dir = Path(out_dir) / TASKS_DIR
    tasks_dir.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f"{TMP_PREFIX}{task.id}-", dir=tasks_dir))
    try:
        yield tmp
        _replace_dir(tmp, tasks_dir / task.id)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


def write_failure(task: Task, out_dir, error: str) -> dict:
    """Record a task that failed outside :func:`run_task` (lost worker, executor error) the same way."""
    result = _result_header(task)
    result.update(status="failed", error=error, rows=[])
    with _task_folder(task, out_dir) as tmp:
        (tmp / "task.log").write_text(f"{error}\n")
        return _write_json(tmp / "result.json", result)


def _result_header(task: Task) -> dict:
    return {"id": task.id, **task.identity(), "dataset": task.dataset, "labels": task.labels,
            "host": os.uname().nodename, "pid": os.getpid()}


def run_task(task: Task, out_dir) -> dict:
    """Run one task and write DIR/tasks/<id>/ atomically; returns its result.json content.

    An exception of the method gives status "failed" (error and traceback in the log), not an exception here;
    an interruption leaves nothing behind."""
    with _task_folder(task, out_dir) as tmp:
        with open(tmp / "task.log", "w") as log_fh:
            def log(msg: str) -> None:
                log_fh.write(f"{time.strftime('%H:%M:%S')} {msg}\n")
                log_fh.flush()

            result = _result_header(task)
            load0, tic = os.getloadavg(), time.perf_counter()
            log(f"task {task.id}: {task.method} on {task.dataset} (fingerprint {task.fingerprint}, "
                f"config {task.config_hash}), pid {os.getpid()} on {result['host']}")
            try:
                cfg = build_config(BenchmarkConfig, task.config, source=f"task {task.id}")
                out = run_method(task.dataset, cfg, task.method, log=log)
                rows = [{**row, **task.labels} for row in out.rows]
                for i, (row, traj) in enumerate(zip(rows, out.trajectories)):
                    if traj is not None:
                        row["trajectory_file"] = f"trajectory_{i}.txt"
                        write_tum(tmp / row["trajectory_file"], traj)
                if out.arrays:
                    np.savez_compressed(tmp / "arrays.npz", **out.arrays)
                result.update(status="done", rows=rows, dataset_info=out.dataset_info)
            except Exception as exc:  # noqa: BLE001 - reported as a failed task, the others go on
                log(traceback.format_exc().rstrip())
                result.update(status="failed", error=f"{type(exc).__name__}: {exc}"[:500], rows=[])
            result.update(wall_seconds=time.perf_counter() - tic, loadavg_start=list(load0),
                          loadavg_end=list(os.getloadavg()), peak_rss_mb=peak_rss_mb())
            log(f"{result['status']} in {result['wall_seconds']:.1f} s" +
                (f": {result['error']}" if result.get("error") else ""))
        return _write_json(tmp / "result.json", result)


def load_result(task: Task, out_dir) -> dict | None:
    """The stored result of ``task`` if it is for the same identity (else None)."""
    path = Path(out_dir) / TASKS_DIR / task.id / "result.json"
    try:
        doc = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    if any(doc.get(k) != v for k, v in task.identity().items()):
        return None
    return doc


def remove_stale_temporaries(out_dir) -> None:
    """Temporary folders of tasks that were killed (run once before new work; one run per folder at a time)."""
    tasks_dir = Path(out_dir) / TASKS_DIR
    if tasks_dir.is_dir():
        for p in tasks_dir.iterdir():
            if p.name.startswith(TMP_PREFIX):
                shutil.rmtree(p, ignore_errors=True)


# ------------------------------------------------------------------------------------------------------------
# executors: results(fn, args_list) yields (index, ok, value or error text) as calls finish
# ------------------------------------------------------------------------------------------------------------

def _error_text(exc: BaseException) -> str:
    return f"{type(exc).__name__}: {exc}"[:500]


class LocalExecutor:
    """``jobs`` = 1: calls run in this process, in order (in one spawned process if this one's Taichi already
    runs with another thread count than ``threads``). More: a spawn process pool of ``jobs`` workers with
    ``threads`` Taichi threads each (default: the CPU count divided among the workers). A worker that dies
    (crash, out of memory) fails only the call it was running: the calls in flight with it are retried one at a time
    in a fresh pool, and the one that kills its worker again alone is reported failed."""

    name = "local"

    def __init__(self, jobs: int = 1, threads: int | None = None):
        self.jobs = max(1, int(jobs))
        self.threads = threads
        if not threads and self.jobs > 1:
            self.threads = max(1, runtime.available_cores() // self.jobs)
        self.running = 0
        self.on_interrupt = None  # called after the workers are stopped on Ctrl-C

    def describe(self) -> str:
        threads = self.threads or runtime.num_threads()
        return f"local, {self.jobs} job{'s' if self.jobs > 1 else ''} x {threads} thread{'s' if threads > 1 else ''}"

    def close(self) -> None:
        pass

    def _in_process(self) -> bool:
        """One job runs here unless this process's Taichi already runs with another thread count."""
        return self.jobs == 1 and (not self.threads or not runtime._state["initialized"]
                                   or runtime.num_threads() == self.threads)

    def results(self, fn, args_list):
        if self._in_process():
            yield from self._serial(fn, args_list)
        else:
            yield from self._pool(fn, args_list)

    def _serial(self, fn, args_list):
        for i, args in enumerate(args_list):
            try:
                value = call_in_worker(fn, args, self.threads)
                ok = True
            except Exception as exc:  # noqa: BLE001
                value, ok = _error_text(exc), False
            self.running = int(i + 1 < len(args_list))  # the next one starts when this result is taken
            yield i, ok, value

    def _new_pool(self):
        import multiprocessing
        from concurrent.futures import ProcessPoolExecutor

        exit_if_spawn_bootstrapping()  # in a pool worker re-running an unguarded script: one line, a known exit
        return ProcessPoolExecutor(max_workers=self.jobs, mp_context=multiprocessing.get_context("spawn"),
                                   initializer=_pool_initializer, initargs=(self.threads,))

    def _pool(self, fn, args_list):
        """Calls run ``jobs`` at a time. When a worker dies the whole pool breaks and every call in flight fails
        with it, the innocent ones too; those calls are retried one at a time (after the first pass), so a call
        that kills its worker again alone is the one reported failed, and never the calls that ran beside it."""
        from concurrent.futures import FIRST_COMPLETED, wait
        from concurrent.futures.process import BrokenProcessPool

        queue = list(range(len(args_list)))[::-1]  # pop() takes the next one
        alone: list = []  # calls in flight when the pool broke: retried one at a time
        pool = self._new_pool()
        inflight: dict = {}
        lost = "worker process died (crash or out of memory), twice"
        try:
            while queue or alone or inflight:
                while queue and len(inflight) < self.jobs:  # submit only what can run now: a broken pool
                    i = queue.pop()                          # then fails only the calls that were running
                    inflight[pool.submit(call_in_worker, fn, args_list[i], self.threads)] = i
                if not queue and alone and not inflight:
                    i = alone.pop(0)
                    inflight[pool.submit(call_in_worker, fn, args_list[i], self.threads)] = -1 - i
                self.running = len(inflight)
                done, _ = wait(list(inflight), return_when=FIRST_COMPLETED)
                broken = False
                for fut in done:
                    i = inflight.pop(fut)
                    retried, i = i < 0, (-1 - i if i < 0 else i)
                    try:
                        value = fut.result()
                    except BrokenProcessPool:
                        broken = True
                        if _exit_codes(pool) & {UNGUARDED_MAIN_EXIT}:  # the same for every call: no retry
                            yield i, False, UNGUARDED_MAIN
                        elif retried:
                            yield i, False, lost
                        else:
                            alone.append(i)
                        continue
                    except Exception as exc:  # noqa: BLE001
                        self.running = min(len(inflight) + len(queue) + len(alone), self.jobs)
                        yield i, False, _error_text(exc)
                        continue
                    self.running = min(len(inflight) + len(queue) + len(alone), self.jobs)
                    yield i, True, value
                if broken:
                    for fut, i in list(inflight.items()):  # the pool is gone: these were running too
                        inflight.pop(fut)
                        alone.append(i)  # never a retried call: those run alone
                    pool.shutdown(wait=False, cancel_futures=True)
                    pool = self._new_pool()
        except BaseException:
            _stop_pool(pool)
            if self.on_interrupt:
                self.on_interrupt()
            raise
        finally:
            self.running = 0
        pool.shutdown(wait=True)


def _pool_initializer(threads: int | None) -> None:
    """Spawned pool worker: killed with its parent (also on SIGKILL), ignores Ctrl-C (the parent stops the workers
    and cleans up), sets up Taichi."""
    import signal

    from ti_cmax.workers import die_with_parent

    die_with_parent()
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    setup_process(threads)


def _exit_codes(pool, wait: float = 5.0) -> set:
    """Exit codes of a broken pool's worker processes, waiting up to ``wait`` seconds for them to end: the calls
    fail with BrokenProcessPool before the dead worker has been reaped."""
    procs = _pool_workers(pool)
    deadline = time.monotonic() + wait
    for p in procs:
        with contextlib.suppress(Exception):
            p.join(max(0.0, deadline - time.monotonic()))
    return {p.exitcode for p in procs if p.exitcode is not None}


def _pool_workers(pool) -> list:
    """A process pool's worker processes: the executor keeps them privately (no public way to reach them), and
    forgets them once shut down."""
    return list((getattr(pool, "_processes", None) or {}).values())


def _stop_pool(pool) -> None:
    procs = _pool_workers(pool)
    pool.shutdown(wait=False, cancel_futures=True)
    for p in procs:
        with contextlib.suppress(Exception):
            p.terminate()
    for p in procs:
        with contextlib.suppress(Exception):
            p.join(5)


class DaskExecutor:
    """Calls as dask.distributed tasks on the scheduler at ``address`` (tcp://HOST:PORT) or on a given Client.
    ``threads``: Taichi threads per worker process (default 1: scale out with processes). A task whose worker
    is lost is retried by Dask on another worker, then reported failed (KilledWorker)."""

    name = "dask"

    def __init__(self, address=None, threads: int | None = None, client=None):
        try:
            import distributed  # noqa: F401
        except ImportError:
            raise InputError("--scheduler dask needs dask.distributed: pip install 'ti-cmax[distributed]'") from None
        if client is None and not address:
            raise InputError("--scheduler dask needs --address tcp://HOST:PORT")
        self.address, self.threads = address, threads or 1
        self._owned = client is None
        self._client = client if client is not None else self._connect()  # fail now, before any output
        self.running = 0

    def close(self) -> None:
        if self._owned:
            with contextlib.suppress(Exception):
                self._client.close()

    def describe(self) -> str:
        return f"dask at {self.address or 'a given client'}, {self.threads} thread(s) per worker"

    def _connect(self):
        from distributed import Client

        try:
            return Client(self.address, timeout="20s")
        except (OSError, TimeoutError) as exc:
            raise InputError(f"cannot reach the Dask scheduler: {exc}", source=str(self.address)) from None

    def results(self, fn, args_list):
        from distributed import as_completed

        client = self._client
        futures = []
        try:
            slots = max(1, sum(client.nthreads().values()))
            index = {}
            for i, args in enumerate(args_list):
                fut = client.submit(call_in_worker, fn, args, self.threads, pure=False)
                index[fut.key] = i
                futures.append(fut)
            pending = len(futures)
            for fut in as_completed(futures):
                pending -= 1
                self.running = min(pending, slots)
                i = index[fut.key]
                try:
                    value = fut.result()
                except Exception as exc:  # noqa: BLE001 - KilledWorker (lost worker), or the call raised
                    yield i, False, _error_text(exc)
                    continue
                finally:
                    fut.release()
                yield i, True, value
        except BaseException:
            with contextlib.suppress(Exception):
                client.cancel(futures)
            raise
        finally:
            self.running = 0


# ------------------------------------------------------------------------------------------------------------
# running many
# ------------------------------------------------------------------------------------------------------------

@dataclass
class RunSummary:
    results: list  # result.json contents, in task order
    skipped: set  # ids of the tasks skipped (finished before)
    ran: int
    failed: int
    wall_seconds: float


def run_calls(executor, fn, args_list: list, *, desc: str = "tasks", quiet: bool = False, on_result=None):
    """Run plain calls on ``executor`` with one progress bar; returns [(ok, value or error)] in input order."""
    from tqdm import tqdm

    out = [None] * len(args_list)
    failed = 0
    with tqdm(total=len(args_list), desc=desc, unit="task", file=sys.stderr, disable=quiet or not args_list,
              dynamic_ncols=True, leave=False) as bar:
        for i, ok, value in executor.results(fn, args_list):
            out[i] = (ok, value)
            failed += not ok
            bar.update(1)
            bar.set_postfix(running=executor.running, failed=failed, refresh=False)
            if on_result is not None:
                on_result(i, ok, value, bar.write)
    return out


def run_tasks(tasks: list[Task], out_dir, executor, *, quiet: bool = False, log=None) -> RunSummary:
    """Run the tasks that have no finished result; returns every task's result (stored, new or failed)."""
    tic = time.perf_counter()
    remove_stale_temporaries(out_dir)
    results: list = [None] * len(tasks)
    todo = []
    for k, task in enumerate(tasks):
        stored = load_result(task, out_dir)
        if stored is not None and stored.get("status") == "done":
            results[k] = stored
        else:
            todo.append(k)
    if log and len(todo) < len(tasks):
        log(f"{len(tasks) - len(todo)} of {len(tasks)} tasks already done (same dataset, method and config): skipped")
    failed = 0

    def on_result(i, ok, value, write):
        nonlocal failed
        task = tasks[todo[i]]
        if not ok:
            value = write_failure(task, out_dir, value)
        results[todo[i]] = value
        failed += value.get("status") != "done"
        if log:
            err = f": {value.get('error')}" if value.get("status") != "done" else ""
            wall = value.get("wall_seconds")
            write(f"{task.id}: {value.get('status')}" + (f" in {wall:.1f} s" if wall is not None else "") + err,
                  file=sys.stderr)

    executor.on_interrupt = lambda: remove_stale_temporaries(out_dir)
    run_calls(executor, run_task, [(tasks[k], str(out_dir)) for k in todo], quiet=quiet, on_result=on_result)
    skipped = {t.id for k, t in enumerate(tasks) if k not in set(todo)}
    return RunSummary(results, skipped, len(todo), failed, time.perf_counter() - tic)


def make_executor(scheduler: str = "local", jobs: int = 1, threads: int | None = None, address: str | None = None):
    if scheduler == "local":
        if jobs < 1:
            raise InputError(f"--jobs must be >= 1, got {jobs}")
        return LocalExecutor(jobs, threads)
    if scheduler == "dask":
        return DaskExecutor(address, threads)
    raise InputError(f"--scheduler: expected local or dask, got {scheduler!r}")


__all__ = ["Task", "task_id", "config_hash", "dataset_fingerprint", "run_task", "run_tasks", "run_calls",
           "load_result", "LocalExecutor", "DaskExecutor", "make_executor", "RunSummary", "call_in_worker"]
