"""Writing outputs all-or-nothing, one writer at a time.

``OutputDir`` (``--out DIR``): takes a lock on DIR (a second run into it refuses with one line), yields a hidden
folder inside DIR where the command builds its outputs, and moves the complete set into DIR only when the block
succeeds; a failure, Ctrl-C or SIGTERM leaves DIR as it was. ``atomic_path`` / ``atomic_files`` do the same for
single files: temporary files beside the targets, renamed into place together at the end. An operating-system
failure (read-only, permission, disk full, not a folder) becomes one :class:`~ti_cmax.errors.OutputError` naming the
target path and the cause.
"""
from __future__ import annotations

import contextlib
import errno
import os
import resource
import shutil
import signal
import sys
import tempfile
from pathlib import Path

PARTIAL_PREFIX = ".ti-cmax-partial-"  # the folder inside DIR where a run builds its outputs
NEARLY_FULL = 1 << 20  # bytes free under which a short write is put down to a full disk


def current_umask() -> int:
    """The process umask (read by setting and restoring it)."""
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def output_error(exc: OSError, path, tmp=None, name=None):
    """An OSError while writing ``path`` as one OutputError line naming the path (``name``, else the file the error
    names, as its final path rather than its temporary one under ``tmp``) and the cause."""
    from .errors import OutputError

    name = name if name is not None else exc.filename if exc.filename is not None else path
    if tmp is not None and str(name).startswith(str(tmp)):
        name = Path(path) / os.path.relpath(name, tmp)  # the file's final path, not its temporary one
    return OutputError(f"cannot write: {_cause(exc, Path(name))}", source=str(name))


def _cause(exc: OSError, where: Path) -> str:
    """The cause of an OSError in words; a short write without an errno (numpy's tofile) on a full disk says so."""
    if exc.errno:
        return os.strerror(exc.errno)  # not exc.strerror: HDF5 puts a page of its own there
    text = str(exc) or type(exc).__name__
    folder = next((d for d in (where, *where.parents) if d.is_dir()), None)
    with contextlib.suppress(OSError, AttributeError, ValueError, TypeError):  # TypeError: no folder exists
        st = os.statvfs(folder)
        if st.f_bavail * st.f_frsize < NEARLY_FULL:
            return f"{os.strerror(errno.ENOSPC)} ({text})"
        if resource.getrlimit(resource.RLIMIT_FSIZE)[0] != resource.RLIM_INFINITY:
            return f"{os.strerror(errno.EFBIG)} ({text})"
    return text


@contextlib.contextmanager
def _signals_held():
    """Ctrl-C and SIGTERM wait while outputs are renamed into place (delivered right after): a set is never half
    moved by them."""
    held = {signal.SIGINT, signal.SIGTERM}
    try:
        old = signal.pthread_sigmask(signal.SIG_BLOCK, held)
    except (AttributeError, ValueError, OSError):  # no pthread_sigmask (Windows)
        old = None
    try:
        yield
    finally:
        if old is not None:
            signal.pthread_sigmask(signal.SIG_SETMASK, old)


def make_folders(folder: Path) -> list[Path]:
    """Create ``folder`` and its missing parents; returns those created, innermost first. A parent that exists and
    is not a folder is the OSError "Not a directory" naming it (mkdir said "File exists")."""
    created = [d for d in (folder, *folder.parents) if not os.path.lexists(d)]
    existing = created[-1].parent if created else folder
    if not existing.is_dir():
        raise NotADirectoryError(errno.ENOTDIR, os.strerror(errno.ENOTDIR), str(existing))
    folder.mkdir(parents=True, exist_ok=True)
    return created


def check_output_file(path) -> None:
    """Before any work: a file output that could not be written ends the run at once, in one line: an existing
    folder of that name, a file among its parents, or a parent folder not writable (read-only, permission)."""
    from .errors import OutputError

    path = Path(path)
    if path.is_dir():
        raise OutputError("is a folder; expected a file name", source=str(path))
    existing = next((d for d in path.parents if os.path.lexists(d)), Path("."))
    if not existing.is_dir():
        raise OutputError(f"cannot write: {os.strerror(errno.ENOTDIR)}", source=str(existing))
    if not os.access(existing, os.W_OK | os.X_OK):
        code = errno.EROFS if _read_only(existing) else errno.EACCES
        raise OutputError(f"cannot write: {os.strerror(code)}", source=str(existing))


def _read_only(folder: Path) -> bool:
    try:
        return bool(os.statvfs(folder).f_flag & os.ST_RDONLY)
    except (OSError, AttributeError):
        return False


@contextlib.contextmanager
def atomic_files(*paths: str | os.PathLike):
    """Yield one temporary path beside each target; when the block succeeds rename all of them into place (together,
    Ctrl-C held off), else remove them: a target is either untouched or complete."""
    from .errors import raise_if_interrupted

    raise_if_interrupted()  # a Ctrl-C the command line received and third-party code swallowed: write nothing
    targets = [Path(p) for p in paths]
    tmps: list[Path] = []
    created: list[Path] = []
    try:
        try:
            for path in targets:
                if path.is_dir():
                    check_output_file(path)
                created += make_folders(path.parent)
                fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=path.suffix or ".tmp", dir=path.parent)
                os.close(fd)
                tmps.append(Path(tmp))
                os.chmod(tmp, 0o666 & ~current_umask())  # mkstemp makes 0600; the output gets open()'s mode
        except OSError as exc:  # a file among the parents, a read-only folder: name the target, not mkstemp's file
            target = targets[len(tmps)]
            raise output_error(exc, target, name=exc.filename if exc.filename not in (None, "") and
                               not Path(exc.filename).name.startswith(f".{target.name}.") else target) from None
        try:
            yield tmps
            with _signals_held():
                for tmp, path in zip(tmps, targets):
                    os.replace(tmp, path)
        except OSError as exc:
            raise _map_tmp_error(exc, tmps, targets) from None
    except BaseException:
        for tmp in tmps:
            with contextlib.suppress(FileNotFoundError):
                os.unlink(tmp)
        for d in created:  # innermost first, only while empty
            with contextlib.suppress(OSError):
                d.rmdir()
        raise


def _map_tmp_error(exc: OSError, tmps: list[Path], targets: list[Path]):
    """An OSError naming a temporary file (or none), as the error of its target."""
    for tmp, path in zip(tmps, targets):
        if exc.filename is None or str(exc.filename) == str(tmp):
            return output_error(exc, path, name=path)
    return output_error(exc, targets[0])


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike, suffix: str | None = None):
    """Yield a temp file path in the target's folder; on success move it onto ``path`` (see atomic_files)."""
    with atomic_files(path) as (tmp,):
        yield tmp


class OutputLock:
    """An exclusive lock on an output folder (created if missing) for one run: a second run into the same folder
    refuses with one line instead of interleaving its files with the first. The lock is an ``flock`` on the
    folder itself (no lock file left behind) and ends with the process, however it ends."""

    def __init__(self, path: str | os.PathLike):
        self.path = Path(path)
        self.created: list[Path] = []
        self._fd: int | None = None

    def acquire(self) -> Path:
        from .errors import OutputError

        path = self.path
        if path.exists() and not path.is_dir():
            raise OutputError("output path exists and is not a folder", source=str(path))
        try:
            self.created = make_folders(path)
            self._fd = os.open(path, os.O_RDONLY)
        except OSError as exc:
            self.release()
            raise output_error(exc, path) from None
        try:
            import fcntl

            fcntl.flock(self._fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except ImportError:  # no fcntl (Windows): no lock
            pass
        except OSError as exc:
            self.release(remove=False)
            if exc.errno in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES):
                raise OutputError("another ti-cmax run is writing to this folder", source=str(path)) from None
            raise output_error(exc, path) from None
        return path

    def release(self, remove: bool = True) -> None:
        """Unlock; with ``remove``, delete the folders the lock made while they are empty (a failed first run)."""
        if self._fd is not None:
            with contextlib.suppress(ImportError, OSError):  # unlocked also for a forked child holding the folder open
                import fcntl

                fcntl.flock(self._fd, fcntl.LOCK_UN)
            os.close(self._fd)
            self._fd = None
        if remove:
            for d in self.created:  # innermost first
                with contextlib.suppress(OSError):
                    d.rmdir()
        self.created = []

    def __enter__(self) -> Path:
        return self.acquire()

    def __exit__(self, exc_type, exc, tb):
        self.release(remove=exc_type is not None)
        return False


class OutputDir:
    """Context manager for a command's output folder ``--out DIR``: locked, built aside, moved in at the end.

    Yields a hidden folder inside DIR; the command writes there. On success each entry is renamed into DIR (an
    existing file or folder of that name replaced whole), with Ctrl-C held off; on failure or interruption the
    hidden folder is removed and DIR is as before (and removed if this run created it). A run killed outright leaves
    only its hidden folder, which the next run into DIR removes.
    """

    def __init__(self, path: str | os.PathLike):
        self.path = Path(path)
        self._lock = OutputLock(path)
        self._tmp: Path | None = None

    def __enter__(self) -> Path:
        from .errors import raise_if_interrupted

        raise_if_interrupted()  # a Ctrl-C the command line received and third-party code swallowed: write nothing
        self._lock.acquire()
        try:
            for stale in self.path.glob(PARTIAL_PREFIX + "*"):  # of a killed run: the lock says it is over
                shutil.rmtree(stale, ignore_errors=True)
            with _signals_held():  # a Ctrl-C comes once the folder is known (and removed below), not inside mkdtemp
                self._tmp = Path(tempfile.mkdtemp(prefix=PARTIAL_PREFIX, dir=self.path))
            os.chmod(self._tmp, 0o777 & ~current_umask())
        except BaseException as exc:  # (a Ctrl-C right after mkdtemp too: its folder must not stay behind)
            if self._tmp is not None:
                shutil.rmtree(self._tmp, ignore_errors=True)
            self._lock.release()
            if isinstance(exc, OSError):
                raise output_error(exc, self.path) from None
            raise
        return self._tmp

    def __exit__(self, exc_type, exc, tb):
        from .errors import OutputError

        tmp, raised = self._tmp, exc
        try:
            if exc_type is None:
                with _signals_held():
                    self._commit(tmp)
        except BaseException as err:  # noqa: B036 - the cleanup below runs, then it is raised again
            raised = err
        mapped = None
        if isinstance(raised, OSError):  # before the clean-up: a full disk is still full when the cause is read
            mapped = output_error(raised, self.path, tmp)
        elif isinstance(raised, OutputError) and str(tmp) in str(raised):  # of an atomic file inside: its final path
            mapped = OutputError(str(raised).replace(str(tmp), str(self.path)))
        shutil.rmtree(tmp, ignore_errors=True)
        self._lock.release(remove=raised is not None)
        if mapped is not None:
            raise mapped from None
        if raised is not None and raised is not exc:
            raise raised
        return False

    def _commit(self, tmp: Path) -> None:
        """Rename every entry of ``tmp`` into the output folder; a folder it replaces is moved aside first."""
        for name in sorted(os.listdir(tmp)):
            src, dst = tmp / name, self.path / name
            if (dst.is_dir() and not dst.is_symlink()) or (src.is_dir() and os.path.lexists(dst)):
                aside = tmp / f".replaced-{name}"
                os.rename(dst, aside)
            os.replace(src, dst)


def peak_rss_mb() -> float:
    """Peak resident set size of this process so far (MB; ru_maxrss is KiB on Linux, bytes on macOS)."""
    r = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return r / (1024.0 * 1024.0) if sys.platform == "darwin" else r / 1024.0


def write_report(directory: str | os.PathLike, report: dict) -> None:
    """``directory/report.json``: ``report`` as strict JSON, with the kernel engine of the run (name, version) and
    the run's status and reasons (ti_cmax.status; derived here unless the caller did, with the time ranges)."""
    import json

    from ti_cmax.kernels.engine import engine_info

    from .status import apply_status

    if "reasons" not in report:
        apply_status(report)

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
