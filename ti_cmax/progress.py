"""Progress bars on stderr (tqdm), silenced with TI_CMAX_NO_PROGRESS=1 or ``quiet``."""
from __future__ import annotations

import os
import sys

from tqdm import tqdm

_QUIET = {"value": os.environ.get("TI_CMAX_NO_PROGRESS", "") not in ("", "0")}


def set_quiet(quiet: bool) -> None:
    _QUIET["value"] = bool(quiet)


def progress(total=None, desc: str = "", unit: str = "it", **kw) -> tqdm:
    """A tqdm bar on stderr; ``bar.update(n)`` as work advances."""
    return tqdm(total=total, desc=desc, unit=unit, file=sys.stderr, disable=_QUIET["value"],
                dynamic_ncols=True, leave=False, **kw)
