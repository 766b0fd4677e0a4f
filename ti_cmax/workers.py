"""Worker processes end with the process that started them, however it ends (SIGKILL included).

A worker killed with its parent cannot linger: the back-end worker blocked on a full pipe, or compiling kernels,
held 140-220 MB for minutes after ``kill -9`` of ``slam`` (and kept multiprocessing's resource tracker alive with
it: the tracker ends when the last process holding its pipe does). On Linux the kernel delivers SIGKILL to the
worker when its parent dies (``prctl(PR_SET_PDEATHSIG)``); elsewhere a daemon thread watches the parent's pid.
"""
from __future__ import annotations

import os
import sys

PR_SET_PDEATHSIG = 1  # <sys/prctl.h>


def _parent_death_signal(signum: int) -> bool:
    """Ask Linux to send ``signum`` to this process when its parent dies; False where that is not available."""
    if not sys.platform.startswith("linux"):
        return False
    try:
        import ctypes

        libc = ctypes.CDLL(None, use_errno=True)
        return libc.prctl(PR_SET_PDEATHSIG, signum, 0, 0, 0) == 0
    except (OSError, AttributeError):
        return False


def _watch_parent(parent_pid: int, poll: float = 1.0) -> None:
    import threading
    import time

    def watch():
        while True:
            time.sleep(poll)
            if os.getppid() != parent_pid:  # reparented: the parent is gone
                os._exit(1)

    threading.Thread(target=watch, name="ti_cmax-parent-watch", daemon=True).start()


def die_with_parent() -> None:
    """Call first thing in a multiprocessing worker: it is killed when its parent process dies. The parent's pid
    comes from multiprocessing (a parent that died before this call is noticed at once)."""
    import multiprocessing
    import signal

    parent = multiprocessing.parent_process()
    if parent is None or parent.pid is None:
        return
    linux = _parent_death_signal(signal.SIGKILL)
    if os.getppid() != parent.pid:  # it died before the signal was asked for
        os._exit(1)
    if not linux:
        _watch_parent(parent.pid)
