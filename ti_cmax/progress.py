"""Progress bars on stderr (tqdm), silenced with TI_CMAX_NO_PROGRESS=1 or ``quiet`` (``--quiet``).

A run shows one bar per stage (:func:`stage` for start-up and compilation, :class:`StageBars` for reading, the
front-end and the back-end over seconds of data); each reaches 100 % when its stage ends and stays on screen.

Bars in seconds of data (``unit="s"``) show rounded figures and the speed against real time,
``slam: 62%|####  | 3.07/4.95 s of data [00:12<00:07, 0.25x real time]``; bars of counts use SI prefixes
(``1.20M/15.5M ev``).
"""
from __future__ import annotations

import contextlib
import functools
import os
import sys

_QUIET = {"value": os.environ.get("TI_CMAX_NO_PROGRESS", "") not in ("", "0")}

_DATA_BAR = "{desc}: {percentage:3.0f}%|{bar}| {n:.2f}/{total:.2f} s of data [{elapsed}<{remaining}, {speed}]"
_DATA_OPEN = "{desc}: {n:.2f} s of data [{elapsed}, {speed}]"


def set_quiet(quiet: bool) -> None:
    _QUIET["value"] = bool(quiet)


def is_quiet() -> bool:
    return _QUIET["value"]


@functools.lru_cache(maxsize=None)
def bar_classes() -> tuple[type, type]:
    """(Bar, DataBar), the tqdm bars; tqdm is imported on the first bar shown (~0.03 CPU s of start-up)."""
    from tqdm import tqdm

    class Bar(tqdm):
        """tqdm without its monitor thread (it only adjusts bars that update too rarely, and ours update with the
        data): a process with one thread can fork a back-end worker (pipelines/worker.worker_start_method)."""

        monitor_interval = 0

    class DataBar(Bar):
        """A bar over seconds of data: rounded totals, speed as a multiple of real time. ``at(seconds)`` moves it
        to that many seconds from the start of the data; ``done()`` to its total (the last chunk's work counted)."""

        def at(self, seconds: float) -> None:
            limit = self.total if self.total else float("inf")
            step = min(max(float(seconds), 0.0), limit) - self.n
            if step > 0:
                self.update(step)

        def done(self) -> None:
            if self.total:
                self.at(self.total)

        @property
        def format_dict(self):
            d = super().format_dict
            rate = d.get("rate") or (d["n"] / d["elapsed"] if d.get("elapsed") else None)
            d["speed"] = f"{rate:.2f}x real time" if rate else "? x real time"
            return d

    return Bar, DataBar


class QuietBar:
    """A bar while quiet: what a disabled tqdm bar does (nothing counted, nothing shown) without importing tqdm.
    Anything else asked of it is asked of a disabled tqdm bar made then."""

    def __init__(self, data: bool, **kw):
        self.n, self.total = 0, kw.get("total")
        self._data, self._kw = data, kw

    def update(self, n=1) -> None:
        pass

    def at(self, seconds: float) -> None:
        pass

    def done(self) -> None:
        pass

    def refresh(self, *args, **kwargs) -> None:
        pass

    def close(self) -> None:
        pass

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return False

    def __getattr__(self, name):
        if name.startswith("_"):
            raise AttributeError(name)
        disabled = bar_classes()[1 if self._data else 0](**self._kw)
        return getattr(disabled, name)


def _bar(data: bool = False, **kw):
    """A tqdm bar (DataBar if ``data``), or a QuietBar while quiet."""
    if kw.get("disable"):
        return QuietBar(data, **kw)
    return bar_classes()[1 if data else 0](**kw)


def progress(total=None, desc: str = "", unit: str = "it", **kw):
    """A tqdm bar on stderr; ``bar.update(n)`` as work advances. ``unit="s"``: seconds of data."""
    common = dict(desc=desc, file=sys.stderr, disable=_QUIET["value"], dynamic_ncols=True,
                  leave=kw.pop("leave", False))
    if unit == "s":
        total = None if total is None or not 0 < total < float("inf") else float(total)  # NaN/inf: open bar
        return _bar(True, total=total, unit="s", bar_format=_DATA_BAR if total else _DATA_OPEN, **common, **kw)
    kw.setdefault("unit_scale", True)
    return _bar(total=total, unit=unit, **common, **kw)


_STAGE_BAR = "{desc}: {percentage:3.0f}%|{bar}| [{elapsed}]"


@contextlib.contextmanager
def stage(desc: str = "start-up and compile"):
    """A bar for one step of unknown length (Taichi's start-up, kernel compilation): 0 % while it runs, 100 % when
    it is done; it stays on screen."""
    bar = _bar(total=1, desc=desc, file=sys.stderr, disable=_QUIET["value"], dynamic_ncols=True, leave=True,
               bar_format=_STAGE_BAR)
    try:
        yield bar
        bar.update(1)
    finally:
        bar.close()


class StageBars:
    """One :class:`DataBar` per stage of a run over seconds of data (e.g. reading, front-end, back-end), stacked;
    ``at(stage, t)`` moves a stage to data time ``t`` (absolute; the first time given is the start of the data),
    ``done()`` takes every stage to 100 % once the run has ended."""

    def __init__(self, total, stages: tuple[str, ...], prefix: str = ""):
        self.t0: float | None = None
        self.bars = {name: progress(total=total, desc=f"{prefix}{name}", unit="s", leave=True, position=i)
                     for i, name in enumerate(stages)}

    def start(self, t0: float) -> None:
        if self.t0 is None:
            self.t0 = float(t0)

    def at(self, name: str, t: float | None) -> None:
        if t is not None and self.t0 is not None:
            self.bars[name].at(t - self.t0)

    def done(self) -> None:
        for bar in self.bars.values():
            bar.done()

    def close(self) -> None:
        for bar in self.bars.values():
            bar.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
        return False
