"""User-facing errors: one clear line, caught by the CLI and printed without a traceback."""
import os


class WorkerLost(RuntimeError):
    """A worker process of ours ended without a result (killed from outside, out of memory): not a bug in the input
    nor in the code, so the CLI reports it in one line (exit 1)."""


class InputError(ValueError):
    """Bad input data or configuration. The message names the file, line or field and what was expected."""

    def __init__(self, message: str, *, source: str | None = None, line: int | None = None):
        where = ""
        if source is not None:
            where = f"{source}"
            if line is not None:
                where += f", line {line}"
            where += ": "
        super().__init__(where + message)
        self.source = source
        self.line = line


class OutputError(InputError):
    """An output that cannot be written (read-only, permission, disk full, not a folder, locked by another run):
    one line naming the path and the cause, exit 2 as for bad input."""


def exception_line(exc: BaseException, limit: int = 200) -> str:
    """A third-party exception as one short line for an InputError: its first non-blank line of text (some span
    many, such as a parser quoting the whole document), cut to ``limit`` characters, or its type's name."""
    text = next((line.strip() for line in str(exc).splitlines() if line.strip()), type(exc).__name__)
    return text if len(text) <= limit else text[:limit - 3] + "..."


def os_error_line(exc: OSError) -> str:
    """An operating-system error as one line: the path(s) it names, then the cause."""
    cause = exc.strerror or (os.strerror(exc.errno) if exc.errno else str(exc) or type(exc).__name__)
    where = ""
    if exc.filename is not None:
        where = f"{exc.filename}"
        if getattr(exc, "filename2", None) is not None:
            where += f" -> {exc.filename2}"
        where += ": "
    return where + cause


def missing_extra(what: str, package: str, extra: str) -> str:
    """The message for an optional dependency that is not installed: how to add it from PyPI or a checkout."""
    return (f"{what} needs the '{package}' package: pip install {package} "
            f"(or, in a checkout of ti_cmax: pip install -e \".[{extra}]\")")


# The command line's Ctrl-C / SIGTERM handlers (cli.main) note the interruption before they raise it: a third-party
# bare ``except:`` can swallow the KeyboardInterrupt (Taichi's kernel decorator does, ~0.5 s of a command's start-up
# while Taichi and the kernels import: the run then went on and ended with exit 0 and every output written).
# ``raise_if_interrupted`` raises it again where a command starts writing (outputs.OutputDir, outputs.atomic_path)
# and when it returns. Only the command line notes interruptions: the Python API never sees one here.
_INTERRUPT: dict = {"type": None}


def note_interrupt(kind: type = KeyboardInterrupt) -> None:
    """Record that the process was interrupted (``kind``: KeyboardInterrupt or a subclass, raised again later)."""
    _INTERRUPT["type"] = kind


def clear_interrupt() -> None:
    _INTERRUPT["type"] = None


def interrupt_pending() -> type | None:
    """The KeyboardInterrupt (sub)class of an interruption the command line received, or None."""
    return _INTERRUPT["type"]


def raise_if_interrupted() -> None:
    """Raise the interruption the command line received, if any (once noted, it stays until the command ends)."""
    if _INTERRUPT["type"] is not None:
        raise _INTERRUPT["type"]()


# A spawned worker process imports the caller's main script again; a script that starts workers at its top level
# (no ``if __name__ == "__main__":``) makes that worker try to start one in turn. Multiprocessing then raises in the
# worker with a page of traceback, and the parent saw only a dead worker (or hung, writing it a large payload).
UNGUARDED_MAIN_EXIT = 86  # the exit code of such a worker, which its parent explains with UNGUARDED_MAIN
UNGUARDED_MAIN = ("a worker process runs the calling script again (Python's spawn), and this script starts worker "
                  "processes at its top level; put that code under `if __name__ == \"__main__\":`")


def exit_if_spawn_bootstrapping() -> None:
    """Called before starting a worker: in a worker still importing the caller's main script, print one line and
    exit with UNGUARDED_MAIN_EXIT."""
    import multiprocessing
    import os
    import sys

    if getattr(multiprocessing.current_process(), "_inheriting", False):
        sys.stderr.write("ti_cmax: a worker process re-ran the calling script's top level\n")
        sys.stderr.flush()
        os._exit(UNGUARDED_MAIN_EXIT)
