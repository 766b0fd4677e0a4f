"""Worker processes die with their parent, also when it is killed outright (SIGKILL): the back-end worker of
``slam``, the task pools' workers and multiprocessing's resource tracker."""
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")


def _children(pid: int) -> set[int]:
    """Processes whose parent is ``pid``."""
    found = set()
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            text = stat.read_text()
        except OSError:
            continue
        fields = text[text.rindex(")") + 2:].split()
        if int(fields[1]) == pid:
            found.add(int(stat.parent.name))
    return found


def _alive(pid: int) -> bool:
    try:
        text = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return False
    return text[text.rindex(")") + 2] != "Z"  # a zombie is dead (its new parent reaps it)


def _wait_gone(pids, seconds: float) -> set[int]:
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        left = {p for p in pids if _alive(p)}
        if not left:
            return left
        time.sleep(0.1)
    return {p for p in pids if _alive(p)}


def _wait_for(predicate, seconds: float, what: str):
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        value = predicate()
        if value:
            return value
        time.sleep(0.1)
    pytest.fail(f"timed out waiting for {what}")


def _kill_and_check(parent: subprocess.Popen, workers: set[int]) -> None:
    try:
        parent.send_signal(signal.SIGKILL)
        parent.wait(timeout=30)
        left = _wait_gone(workers, 5.0)
    finally:
        for pid in workers:
            if _alive(pid):
                os.kill(pid, signal.SIGKILL)
    assert not left, f"still alive 5 s after their parent was killed: {sorted(left)}"


SCRIPT = textwrap.dedent("""
    import sys, time
    from pathlib import Path

    def task(flag):
        Path(flag).touch()
        time.sleep(600)

    def worker(flag):
        from ti_cmax.workers import die_with_parent

        die_with_parent()
        task(flag)

    if __name__ == "__main__":
        flags = Path(sys.argv[2])
        if sys.argv[1] == "process":
            import multiprocessing as mp

            mp.get_context("spawn").Process(target=worker, args=(str(flags / "w0"),)).start()
            time.sleep(600)
        else:
            from ti_cmax.pipelines.evaluation.tasks import LocalExecutor

            for _ in LocalExecutor(jobs=2, threads=1).results(task, [(str(flags / "w0"),), (str(flags / "w1"),)]):
                pass
""")


@pytest.mark.parametrize("kind, n", [("process", 1), ("pool", 2)])
def test_workers_die_with_a_killed_parent(tmp_path, kind, n):
    script = tmp_path / "parent.py"
    script.write_text(SCRIPT)
    flags = tmp_path / "flags"
    flags.mkdir()
    parent = subprocess.Popen([sys.executable, str(script), kind, str(flags)], cwd=tmp_path)
    try:
        _wait_for(lambda: len(list(flags.iterdir())) == n, 90, f"{n} workers to start")
        workers = _children(parent.pid)
    finally:
        if parent.poll() is not None:
            pytest.fail(f"the parent ended early (exit {parent.returncode})")
    assert len(workers) >= n
    _kill_and_check(parent, workers)


def test_slam_worker_and_resource_tracker_die_with_a_killed_slam(tmp_path):
    """SIGKILL of `slam` left the back-end worker and the resource tracker alive (blocked on a pipe, for minutes)."""
    from ti_cmax.simulate import SimulatorConfig, simulate_to_folder

    seq = tmp_path / "seq"
    simulate_to_folder(SimulatorConfig(scene="city", duration=1.0, seed=3), seq, show_progress=False,
                       events_format="h5")
    # replayed at a quarter of real time: the run lasts at least 4 s however fast the machine processes it
    slam = subprocess.Popen([sys.executable, "-m", "ti_cmax.cli", "slam", str(seq), "--out", str(tmp_path / "out"),
                             "--parallel", "--realtime", "--set", "realtime_speed=0.25", "--quiet"],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                            env={**os.environ, "TI_CMAX_NO_PROGRESS": "1"})

    def worker_started():  # forked (the command line of slam) or spawned (multiprocessing's spawn_main)
        kids = _children(slam.pid)
        started = {p for p in kids if any(word in Path(f"/proc/{p}/cmdline").read_bytes()
                                          for word in (b"spawn_main", b"ti_cmax.cli"))}
        return kids if started else None

    try:
        processes = _wait_for(worker_started, 120, "the back-end worker")
        time.sleep(2.0)  # into its start-up (imports, kernel compilation)
        processes |= _children(slam.pid)
    finally:
        if slam.poll() is not None:
            pytest.fail(f"slam ended before it was killed (exit {slam.returncode})")
    _kill_and_check(slam, processes)
