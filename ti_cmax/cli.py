"""The ``ti-cmax`` command line: one module per subcommand in :mod:`ti_cmax.commands`.

Each command module defines ``HELP``, ``add_arguments(parser)`` and ``run(args) -> int``.
Common options (``--config``, ``--set``, ``--threads``, ``--quiet``) are added here. Bad input
ends with one line on stderr and exit code 2, never a traceback; so does an operating-system failure (a path that
cannot be read or written, a full disk).
"""
from __future__ import annotations

import argparse
import importlib
import os
import sys

from .errors import (InputError, WorkerLost, clear_interrupt, interrupt_pending, note_interrupt, os_error_line,
                     raise_if_interrupted)

# subcommand name -> module in ti_cmax.commands
COMMANDS = {
    "simulate": "simulate",
    "info": "info",
    "convert": "convert",
    "frontend": "frontend",
    "slam": "slam",
    "refine": "refine",
    "imu": "imu",
    "map": "map",
    "evaluate": "evaluate",
    "plot": "plot",
    "demo": "demo",
    "benchmark": "benchmark",
    "sweep": "sweep",
    "batch": "batch",
    "baseline": "baseline",
    "grayscale": "grayscale",
    "star-tracking": "star_tracking",
    "super-resolution": "super_resolution",
    "params": "params",
}


def _available_commands(only: str | None = None):
    """(name, module) of each subcommand; with ``only`` (a subcommand's name) that one's module alone, the others'
    None (not imported: some 0.03 CPU s of every command's start-up)."""
    for name, module in COMMANDS.items():
        if only is not None and name != only:
            yield name, None
            continue
        try:
            yield name, importlib.import_module(f"ti_cmax.commands.{module}")
        except ModuleNotFoundError as exc:
            if exc.name == f"ti_cmax.commands.{module}":
                continue  # not implemented yet
            raise


def version_text() -> str:
    """``ti-cmax X (ENGINE Y)``: the kernel engine this process would run, from its installed metadata (no import)."""
    from ti_cmax.kernels.engine import engine_text

    from . import __version__

    return f"ti-cmax {__version__} ({engine_text()})"


class _VersionAction(argparse.Action):
    """``--version``, its text read only when asked (importlib.metadata costs ~30 ms of every command's start-up)."""

    def __init__(self, option_strings, dest=argparse.SUPPRESS, default=argparse.SUPPRESS, help=None):
        super().__init__(option_strings, dest=dest, default=default, nargs=0,
                         help=help or "show the program's version number and exit")

    def __call__(self, parser, namespace, values, option_string=None):
        try:
            text = version_text()
        except InputError as exc:  # a bad TI_CMAX_ENGINE
            parser.exit(2, f"ti-cmax: error: {exc}\n")
        print(text)  # on stdout, as argparse's own version action
        parser.exit()


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """The command line. With ``command`` (the one being run, one of COMMANDS) only that subcommand's module is
    imported and its arguments built: some import what their choices come from (``benchmark``: the suites and
    baselines, ``simulate``: scipy), ~0.5 s of start-up that every other command paid. Without (``--help``, an
    unknown command) every subcommand is listed with its help line."""
    parser = argparse.ArgumentParser(
        prog="ti-cmax", description="CMax-SLAM: rotational motion estimation for event cameras (Taichi CPU)."
    )
    parser.add_argument("--version", action=_VersionAction)
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    for name, module in _available_commands(command if command in COMMANDS else None):
        if module is None:  # not the command being run: listed only
            sub.add_parser(name)
            continue
        p = sub.add_parser(name, help=module.HELP, description=module.HELP)
        if name != command:  # --version, --help: no subcommand builds its arguments (kernel imports)
            continue
        module.add_arguments(p)
        p.add_argument("--config", metavar="FILE.yaml", help="YAML file of parameters")
        p.add_argument("--set", metavar="KEY=VALUE", action="append", default=[], dest="overrides",
                       help="override one parameter (repeatable), e.g. --set num_events_per_packet=20000")
        p.add_argument("--threads", type=_thread_count, default=None,
                       help="CPU threads for the kernels (default: all cores; slam with a back-end worker: half "
                            "per process)")
        p.add_argument("--quiet", action="store_true", help="no progress bars")
        p.set_defaults(_run=module.run)
    return parser


def _thread_count(text: str) -> int:
    """--threads: an integer from 1 to 1024 (argparse reports anything else as one usage error)."""
    import argparse

    try:
        n = int(text)
    except ValueError:
        n = 0
    if not 1 <= n <= 1024:
        raise argparse.ArgumentTypeError(f"expected a thread count from 1 to 1024, got {text!r}")
    return n


def configured_threads(args) -> int | None:
    """``num_threads`` from --set or the --config file (flat or output.num_threads), read before any kernel
    starts; a bad value or file is left to the command's own config load to report."""
    import yaml

    from .config import parse_overrides

    try:
        values = parse_overrides(getattr(args, "overrides", None))
        if getattr(args, "config", None):
            with open(args.config) as fh:
                loaded = yaml.safe_load(fh)
            if isinstance(loaded, dict):
                values = {**loaded, **(loaded.get("output") if isinstance(loaded.get("output"), dict) else {}),
                          **values}
    except (InputError, OSError, ValueError, yaml.YAMLError):  # ValueError: a file that is not UTF-8 text
        return None
    n = values.get("output.num_threads", values.get("num_threads"))
    return n if isinstance(n, int) and not isinstance(n, bool) and n > 0 else None


def main(argv: list[str] | None = None) -> int:
    entry = argv is None  # the process's own command line (the console script, python -m ti_cmax.cli)
    argv = sys.argv[1:] if argv is None else [str(a) for a in argv]
    # the subcommand is the first argument that is not an option (the top level has only --help and --version)
    command = next((a for a in argv if not a.startswith("-")), None)
    name = command if command in COMMANDS else None
    previous: dict = {}
    code = None
    clear_interrupt()
    # Ctrl-C or SIGTERM from here on, also while the command modules, Taichi and the pipelines import (it printed a
    # traceback), is the interruption of a running command: one line, exit 130 (143), outputs removed
    if argv[:1] == ["--version"]:  # what argparse does first with it (exits), without building the command line
        _VersionAction(["--version"])(argparse.ArgumentParser(prog="ti-cmax"), None, None)
    try:
        import signal
        import threading

        if threading.current_thread() is threading.main_thread():
            for sig, handler in ((signal.SIGTERM, _on_sigterm), (signal.SIGINT, _on_sigint)):
                previous[sig] = signal.signal(sig, handler)
        parser = build_parser(command)
        args = parser.parse_args(argv)
        code = _run_command(args)
    except KeyboardInterrupt as exc:
        code = _interrupted(name, exc)
    except Exception:
        if not interrupt_pending():
            raise
        # the interruption, turned into another error by third-party code (see _on_sigint)
        code = _interrupted(name, interrupt_pending()())
    finally:
        clear_interrupt()
        # interrupted, the process only exits now: a second Ctrl-C (a terminal's repeated key, `timeout`'s signal to
        # the process and then to its group) printed a traceback from multiprocessing's exit handler
        ignore = entry and code in (130, 143)
        for sig, handler in previous.items():
            signal.signal(sig, signal.SIG_IGN if ignore else signal.SIG_DFL if handler is None else handler)
    return code


def entry_point() -> None:
    """The process's own command line (the ``ti-cmax`` script, ``python -m ti_cmax.cli``): :func:`main`, then the
    process ends at once, after what its normal end runs that matters (threads joined, the threading and atexit
    hooks, the kernel engine's offline cache written, output flushed) but without the interpreter's teardown of
    every module and object: 0.3-0.8 s of a `slam` run, half its wall time once the results were written."""
    _exit(main())


def _exit(code: int) -> None:
    import atexit
    import threading

    threading._shutdown()  # the interpreter's first step at exit: non-daemon threads joined, their exit hooks run
    if "ti_cmax.kernels.runtime" in sys.modules:
        sys.modules["ti_cmax.kernels.runtime"].shutdown()
    atexit._run_exitfuncs()
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):  # a reader that went away, a closed stream: nothing more to say there
            pass
    os._exit(code)


def _run_command(args) -> int:
    from . import progress

    if args.quiet:
        progress.set_quiet(True)
    try:
        threads = args.threads or configured_threads(args)
        # with --jobs N > 1 or --scheduler dask, --threads is for the worker processes
        if threads and getattr(args, "jobs", 1) == 1 and getattr(args, "scheduler", "local") == "local":
            from .kernels import runtime  # imports the engine: a bad TI_CMAX_ENGINE is an InputError

            runtime.set_num_threads(threads)
        from . import timeline

        timeline.mark("command")  # the interpreter, the command line and the command's module are loaded
        code = int(args._run(args) or 0)
        sys.stdout.flush()  # a closed pipe shows here, not at interpreter exit
        raise_if_interrupted()  # a Ctrl-C that third-party code swallowed (see errors.raise_if_interrupted)
        return code
    except BrokenPipeError:
        # the reader of stdout went away (``ti-cmax evaluate ... | head -2``): end quietly, like a SIGPIPE
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        return 141
    except (InputError, WorkerLost, OSError) as exc:
        if interrupt_pending():  # e.g. Ctrl-C also ended the back-end worker: the interruption, not an error
            return _interrupted(args.command, interrupt_pending()())
        # OSError: a file that vanished or cannot be read, a path that cannot be written (read-only, permission, disk
        # full): the path and the cause; the outputs are removed on the way (outputs.OutputDir, atomic_files)
        text = os_error_line(exc) if isinstance(exc, OSError) else exc
        print(f"ti-cmax {args.command}: error: {text}", file=sys.stderr)
        return 1 if isinstance(exc, WorkerLost) else 2
    except KeyboardInterrupt as exc:
        return _interrupted(args.command, exc)


def _interrupted(command: str | None, exc: KeyboardInterrupt) -> int:
    """The one line and exit code of Ctrl-C (130) or SIGTERM (143)."""
    terminated = isinstance(exc, _Terminated)
    print(f"ti-cmax{' ' + command if command else ''}: {'terminated' if terminated else 'interrupted'}",
          file=sys.stderr)
    return 143 if terminated else 130


class _Terminated(KeyboardInterrupt):
    """SIGTERM (``kill``, a job scheduler's time limit) taken as Ctrl-C is: the command's outputs are removed on the
    way out (OutputDir), a worker process is stopped. Without it the process died with partial outputs."""


def _on_sigterm(signum, frame):
    if isinstance(sys.exc_info()[1], KeyboardInterrupt):  # see _on_sigint
        return
    note_interrupt(_Terminated)
    raise _Terminated()


def _on_sigint(signum, frame):
    """Python's own Ctrl-C handler (KeyboardInterrupt), noting the interrupt first. A KeyboardInterrupt raised inside
    third-party code can be swallowed (a bare ``except:`` in Taichi's kernel decorator, run for every kernel while
    Taichi and our kernels import: the run went on to exit 0 with its outputs) or turned into another error
    (during the init of Taichi's C++ module: ImportError "initialization failed"); see errors.raise_if_interrupted.
    A second Ctrl-C while the first one's KeyboardInterrupt is on its way out (its cleanup: outputs removed, the
    worker stopped) is ignored: raised there, it cut the cleanup short (partial outputs and a traceback)."""
    if isinstance(sys.exc_info()[1], KeyboardInterrupt):
        return
    note_interrupt(KeyboardInterrupt)
    raise KeyboardInterrupt()


if __name__ == "__main__":  # pragma: no cover
    entry_point()
