"""A command's figures drawn in a forked process beside it (``ti-cmax slam``: run.png).

matplotlib costs about 0.5 CPU s to import and run.png about 0.25 s to draw. In the command's own
process both were on its critical path: the imports in a thread beside the front-end (one GIL), the drawing after
the last window. Forked at the command's start, this process imports them while the command imports its pipeline
(on another core), then waits; at the end it draws while the command writes its other outputs.

``FigureProcess.start()`` forks it only where that pays and is safe: ``fork`` (Linux), 2 or more cores, and no
other thread in this process (a fork copies the locks they hold); elsewhere its jobs run in this process, when
submitted. What is sent must unpickle without the kernel engine (the process does not import it):
plain arrays, Trajectories, :func:`ti_cmax.plots.window_states` instead of the back-end's WindowReports.
"""
from __future__ import annotations

import os
import sys

# imported before the fork (the command needs them too: imported once, inherited), then by the figure process at
# once (what plots.plot_run and the PNG writer load on first use)
SHARED = ("numpy", "ti_cmax.plots")
MODULES = ("matplotlib.figure", "matplotlib.backends.backend_agg", "PIL.Image", "PIL.PngImagePlugin")


def draw(job) -> None:
    """Run one job ``(function, args, kwargs)`` here."""
    function, args, kwargs = job
    function(*args, **kwargs)


def usable() -> bool:
    """Whether a figure process may start now: fork on Linux, 2 or more cores, no other thread in this process, and
    not turned off (``TI_CMAX_FIGURE_PROCESS=0``: on a machine whose cores are all busy with other work the process
    only moves CPU time around, and its imports then compete with the command's start-up)."""
    if not sys.platform.startswith("linux") or os.environ.get("TI_CMAX_FIGURE_PROCESS", "") == "0":
        return False
    try:
        return len(os.sched_getaffinity(0)) >= 2 and len(os.listdir("/proc/self/task")) == 1
    except (AttributeError, OSError):
        return False


class FigureProcess:
    """The forked figure process and its pipe. ``submit(function, *args, **kwargs)`` has it run a job (a function
    of a module, picklable arguments); ``wait()`` returns once every job is done, raising the first job's error
    here, with the process's figures (peak RSS in MB, CPU seconds; empty when the jobs ran here). The jobs of a
    process that is gone (killed) run here: the outputs are complete either way. ``close()`` ends it (on an error
    at once: before the outputs are removed)."""

    def __init__(self, process, conn):
        self._process, self._conn = process, conn
        self._pending: list = []  # jobs sent, not acknowledged yet (run here if the process is lost)
        self.figures: dict = {}

    @property
    def forked(self) -> bool:
        """Whether the jobs run in the figure process (else here, when submitted)."""
        return self._process is not None

    @classmethod
    def start(cls) -> FigureProcess:
        import importlib

        for name in SHARED:
            importlib.import_module(name)
        if not usable():
            return cls(None, None)
        import multiprocessing as mp
        import signal

        ctx = mp.get_context("fork")
        parent, child = ctx.Pipe()
        process = ctx.Process(target=_serve, args=(child, MODULES), name="ti-cmax-figures", daemon=True)
        # SIGINT blocked from its first instruction (Ctrl-C reaches the whole process group: the command handles it)
        mask = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
        try:
            sys.stdout.flush()  # a forked process would write this process's unflushed output again
            sys.stderr.flush()
            process.start()
        except OSError:  # no memory or process left for a fork: draw here
            return cls(None, None)
        finally:
            signal.pthread_sigmask(signal.SIG_SETMASK, mask)
        child.close()
        return cls(process, parent)

    def submit(self, function, *args, **kwargs) -> None:
        job = (function, args, kwargs)
        if self._process is not None:
            try:
                self._conn.send(job)
                self._pending.append(job)
                return
            except (OSError, EOFError):  # the process is gone
                self._lost()
        draw(job)

    def wait(self) -> dict:
        """Every job done (its error raised here); the figure process's {"peak_rss_mb", "cpu_seconds"} ({} when
        the jobs ran here)."""
        while self._pending:
            try:
                kind, value = self._conn.recv()
            except (OSError, EOFError):
                self._lost()
                break
            self._pending.pop(0)
            if kind == "error":
                self.close()
                raise value
            self.figures = value
        return self.figures

    def _lost(self) -> None:
        """The process ended unasked: its jobs not acknowledged are run here."""
        pending, self._pending = self._pending, []
        self.close()
        for job in pending:
            draw(job)

    def close(self) -> None:
        if self._process is None:
            return
        process, self._process = self._process, None
        try:
            self._conn.send(None)  # done: it exits
        except (OSError, EOFError):
            pass
        self._conn.close()
        process.join(timeout=1.0)
        if process.is_alive():
            process.terminate()
            process.join(timeout=1.0)

    def __enter__(self) -> FigureProcess:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is not None and self._process is not None:  # the command failed: stop drawing at once
            self._process.terminate()
        self.close()


def _serve(conn, modules) -> None:
    """The figure process: import ``modules``, then run the jobs received until told to stop (None) or the command
    is gone (end of the pipe). Each job is acknowledged with ("ok", {"peak_rss_mb", "cpu_seconds"}) or ("error",
    exception)."""
    import importlib
    import signal
    import time

    from ti_cmax.workers import die_with_parent

    die_with_parent()
    signal.signal(signal.SIGTERM, signal.SIG_DFL)  # the command line's handler came along with the fork
    for name in modules:
        try:
            importlib.import_module(name)
        except Exception:  # noqa: BLE001 - a job that needs it imports it again and reports what fails
            break
    from ti_cmax.outputs import peak_rss_mb

    while True:
        try:
            job = conn.recv()
        except (OSError, EOFError):
            return
        if job is None:
            return
        try:
            draw(job)
            reply = ("ok", {"peak_rss_mb": peak_rss_mb(), "cpu_seconds": time.process_time()})
        except Exception as exc:  # noqa: BLE001 - raised again in the command
            reply = ("error", exc)
        try:
            conn.send(reply)
        except Exception:  # noqa: BLE001 - an exception that does not pickle: its text
            conn.send(("error", RuntimeError(f"{type(reply[1]).__name__}: {reply[1]}")))
