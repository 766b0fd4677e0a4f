"""Writing outputs without leaving partial files behind.

``atomic_path`` yields a temporary path beside the target and renames it into place only when
the block succeeds. ``OutputDir`` creates ``--out DIR`` and, if the command fails, removes what the
command wrote there (and the directory itself if it created it).
"""
from __future__ import annotations

import contextlib
import os
import resource
import sys
import shutil
import tempfile
from pathlib import Path

from .errors import InputError, raise_if_interrupted


def current_umask() -> int:
    """The process umask (read by setting and restoring it)."""
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike, suffix: str | None = None):
    """Yield a temp file path in the target's folder; on success move it onto ``path``."""
    raise_if_interrupted()  # a Ctrl-C the command line received and third-party code swallowed: write nothing
    path = Path(path)
    created = [d for d in path.parents if not d.exists()]  # folders made for it, removed again on failure
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=suffix or path.suffix or ".tmp", dir=path.parent)
    os.close(fd)
    os.chmod(tmp, 0o666 & ~current_umask())  # mkstemp makes 0600; the output gets the mode open() would give it
    try:
        yield Path(tmp)
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        for d in created:  # innermost first; only while empty (Ctrl-C during `map --out new/m.png` left new/)
            with contextlib.suppress(OSError):
                d.rmdir()
        raise


class OutputDir:
    """Context manager for a command's output folder: all-or-nothing on failure."""

    def __init__(self, path: str | os.PathLike):
        self.path = Path(path)
        self._created = False
        self._before: set[str] = set()

    def __enter__(self) -> Path:
        raise_if_interrupted()  # a Ctrl-C the command line received and third-party code swallowed: write nothing
        if self.path.exists() and not self.path.is_dir():
            raise InputError("output path exists and is not a folder", source=str(self.path))
        if not self.path.exists():
            self.path.mkdir(parents=True)
            self._created = True
        self._before = set(os.listdir(self.path))
        return self.path

    def __exit__(self, exc_type, exc, tb):
        if exc_type is None:
            return False
        if self._created:
            shutil.rmtree(self.path, ignore_errors=True)
        else:
            for name in set(os.listdir(self.path)) - self._before:
                p = self.path / name
                shutil.rmtree(p, ignore_errors=True) if p.is_dir() else p.unlink(missing_ok=True)
        return False


def peak_rss_mb() -> float:
    """Peak resident set size of this process so far (MB; ru_maxrss is KiB on Linux, bytes on macOS)."""
    r = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return r / (1024.0 * 1024.0) if sys.platform == "darwin" else r / 1024.0


def write_report(directory: str | os.PathLike, report: dict) -> None:
    """``directory/report.json``: ``report`` as strict JSON, with the kernel engine of the run (name, version)."""
    import json

    from ti_cmax.kernels.engine import engine_info

    doc = json_ready({**report, "engine": engine_info()})
    (Path(directory) / "report.json").write_text(json.dumps(doc, indent=2, default=float))


def json_ready(obj):
    """NaN/inf -> None, numpy scalars and arrays -> Python: every JSON file we write is strict JSON (a NaN, e.g. an
    error over a sequence shorter than its window, made report.json unreadable by strict parsers)."""
    import math

    import numpy as np

    if isinstance(obj, dict):
        return {k: json_ready(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [json_ready(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return json_ready(obj.tolist())
    if isinstance(obj, (np.floating, float)):
        return float(obj) if math.isfinite(obj) else None
    if isinstance(obj, np.integer):
        return int(obj)
    if isinstance(obj, np.bool_):
        return bool(obj)
    return obj
