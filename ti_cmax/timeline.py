"""Named points in the life of a process: wall clock (epoch seconds) and the process's CPU seconds at each.

A run's steady-state figures (us per event) leave out what a user also waits for: the interpreter and imports, the
kernels' preparation, waiting for a worker, writing the outputs. ``mark(name)`` notes a point; report.json keeps
them (``timeline_seconds``: this process's, ``backend_process.timeline_seconds``: the worker's), and the
whole-process benchmark (pipelines/evaluation/bench_process.py) lines them up with the moment it launched the
command. Epoch seconds, because points of two processes are compared.
"""
from __future__ import annotations

import time

_POINTS: dict[str, tuple[float, float]] = {}


def mark(name: str) -> None:
    """Note the wall clock and this process's CPU time at ``name`` (a later mark of the same name replaces it)."""
    _POINTS[name] = (time.time(), time.process_time())


def points() -> dict[str, list[float]]:
    """``{name: [epoch wall seconds, process CPU seconds]}`` in the order marked."""
    return {name: [wall, cpu] for name, (wall, cpu) in _POINTS.items()}


def clear() -> None:
    """Forget every point (a forked worker starts its own timeline)."""
    _POINTS.clear()
