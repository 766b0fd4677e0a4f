"""Progress bars on stderr (tqdm), silenced with TI_CMAX_NO_PROGRESS=1 or ``quiet`` (``--quiet``, which also
silences Taichi's start-up line: see kernels/runtime.py).

Bars in seconds of data (``unit="s"``) show rounded figures and the speed against real time,
``slam: 62%|####  | 3.07/4.95 s of data [00:12<00:07, 0.25x real time]``; bars of counts use SI prefixes
(``1.20M/15.5M ev``).
"""
from __future__ import annotations

import os
import sys

from tqdm import tqdm

_QUIET = {"value": os.environ.get("TI_CMAX_NO_PROGRESS", "") not in ("", "0")}

_DATA_BAR = "{desc}: {percentage:3.0f}%|{bar}| {n:.2f}/{total:.2f} s of data [{elapsed}<{remaining}, {speed}]"
_DATA_OPEN = "{desc}: {n:.2f} s of data [{elapsed}, {speed}]"


def set_quiet(quiet: bool) -> None:
    _QUIET["value"] = bool(quiet)


def is_quiet() -> bool:
    return _QUIET["value"]


class DataBar(tqdm):
    """A bar over seconds of data: rounded totals, speed as a multiple of real time."""

    @property
    def format_dict(self):
        d = super().format_dict
        rate = d.get("rate") or (d["n"] / d["elapsed"] if d.get("elapsed") else None)
        d["speed"] = f"{rate:.2f}x real time" if rate else "? x real time"
        return d


def progress(total=None, desc: str = "", unit: str = "it", **kw) -> tqdm:
    """A tqdm bar on stderr; ``bar.update(n)`` as work advances. ``unit="s"``: seconds of data."""
    common = dict(desc=desc, file=sys.stderr, disable=_QUIET["value"], dynamic_ncols=True, leave=False)
    if unit == "s":
        total = None if total is None or not 0 < total < float("inf") else float(total)  # NaN/inf: open bar
        return DataBar(total=total, unit="s", bar_format=_DATA_BAR if total else _DATA_OPEN, **common, **kw)
    kw.setdefault("unit_scale", True)
    return tqdm(total=total, unit=unit, **common, **kw)
