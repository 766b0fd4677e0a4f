"""The one place that imports the kernel engine: Taichi, or quadrants, its maintained fork (kernels/engine.py says
which: ``TI_CMAX_ENGINE=taichi|quadrants``, else taichi where installed). Both run the same kernel source (``ti``
here is the engine's module); where their internals differ (BoundLaunch), the difference stays in this module.

Every kernel module does ``from ti_cmax.kernels.runtime import ti`` and every public
kernel wrapper calls :func:`ensure_init` before launching. This keeps stdout clean
(the engine prints a banner on import and the arch line on ``ti.init``), pins the CPU
backend with the offline cache, and makes a later switch of fork or arch a one-file
change.

Threads: ``TI_CMAX_THREADS`` (env) or :func:`set_num_threads` before the first kernel (the CLI's ``--threads`` and
``--set num_threads``). Float atomics (the bilinear votes) add in thread-schedule order, so results depend on the
thread count; ``cpu_max_num_threads=1`` is bit-exact run to run (tests/pipelines/test_threads.py).
Fast math (LLVM's reassociation and contraction; the engines' default) is on unless ``TI_CMAX_FAST_MATH=0``: the
two engines build on different LLVM releases, which round differently under fast math (kernel results ~1 ulp
apart, amplified by the optimizers along a run), and agree bit for bit without it at one thread
(tests/pipelines/test_engines.py).
Profiling: ``TI_CMAX_KERNEL_PROFILER=1`` turns on the engine's kernel profiler (see examples/profile_cpu.py).
Start-up: Taichi's per-node source-position messages are shortened (``TI_CMAX_FULL_TAICHI_ERRORS=1`` keeps them).
"""
from __future__ import annotations

import contextlib
import functools
import importlib
import os
import sys
import types

import numpy as np

from .engine import engine_name

ENGINE = engine_name()
# quiet imports: no version check over the network, no banner, no pip import (quadrants' glibc/pip advice)
for _name in ("TI_SKIP_VERSION_CHECK", "QD_MANYLINUX2014_OK"):
    os.environ.setdefault(_name, "ON")
for _name in ("ENABLE_TAICHI_HEADER_PRINT", "ENABLE_QUADRANTS_HEADER_PRINT"):
    os.environ.setdefault(_name, "0")

# BoundLaunch uses the engine's internals: the exact Taichi release, quadrants 1.x from the release tested on
# (as pyproject.toml requires; from, up to but not including)
REQUIRED_VERSION = {"taichi": ((1, 7, 4), (1, 7, 5)), "quadrants": ((1, 3, 3), (2, 0, 0))}[ENGINE]


@contextlib.contextmanager
def _stdout_to_stderr(discard: bool = False):
    """Route file descriptor 1 to 2, or to /dev/null when ``discard`` (the engine's C++ logger writes to fd 1
    directly, and ``ti.init`` prints its arch line with print())."""
    sys.stdout.flush()
    saved = os.dup(1)
    target = os.open(os.devnull, os.O_WRONLY) if discard else 2
    try:
        os.dup2(target, 1)
        yield
    finally:
        sys.stdout.flush()
        os.dup2(saved, 1)
        os.close(saved)
        if discard:
            os.close(target)


class _OnFirstUse(types.ModuleType):
    """Stands for a module in the engine's import; the module itself is imported on first use of an attribute."""

    def __getattr__(self, name):
        if sys.modules.get(self.__name__) is self:
            del sys.modules[self.__name__]
        return getattr(importlib.import_module(self.__name__), name)


@contextlib.contextmanager
def _engine_import_trimmed():
    """Taichi's import, less what a run does not use. Its version check (urllib, http, ssl, email), which
    TI_SKIP_VERSION_CHECK=ON turns off, and dill (it reads the source of kernels typed into an interactive shell):
    ~0.05 CPU s of every command's start-up. With the check off its module is its no-op; dill is imported on first
    use (only Taichi's own module holds the stand-in: any other import of dill gets dill). And its check of every
    decorator for a class body, done without a scan of all loaded modules (_patch_class_check)."""
    if os.environ.get("TI_SKIP_VERSION_CHECK") == "ON" and "taichi._version_check" not in sys.modules:
        check = types.ModuleType("taichi._version_check", "the version check, off (TI_SKIP_VERSION_CHECK=ON)")
        check.start_version_check_thread = lambda: None
        sys.modules[check.__name__] = check
    finder = _PatchedOnImport("taichi.lang.kernel_impl", _patch_class_check)
    sys.meta_path.insert(0, finder)
    stand_in, spec = None, None
    if "dill" not in sys.modules:
        from importlib.util import find_spec

        spec = find_spec("dill")  # where it is, without importing it
    if spec is not None and spec.origin:
        stand_in = sys.modules["dill"] = _OnFirstUse("dill")
        stand_in.__file__ = spec.origin  # what inspect reads of every module in sys.modules (Taichi calls it)
    try:
        yield
    finally:
        if finder in sys.meta_path:
            sys.meta_path.remove(finder)
        if stand_in is not None and sys.modules.get("dill") is stand_in:
            del sys.modules["dill"]


class _PatchedOnImport:
    """A meta path finder: the module ``name``, found as usual, gets ``patch(module)`` right after it executes (before
    the rest of its package's import uses it)."""

    def __init__(self, name: str, patch):
        self.name, self.patch = name, patch

    def find_spec(self, name, path, target=None):
        if name != self.name:
            return None
        from importlib.machinery import PathFinder

        sys.meta_path.remove(self)
        spec = PathFinder.find_spec(name, path, target)
        if spec is None or spec.loader is None or not hasattr(spec.loader, "exec_module"):
            return spec
        execute, patch = spec.loader.exec_module, self.patch

        def exec_module(module):
            execute(module)
            patch(module)

        spec.loader.exec_module = exec_module
        return spec


def _patch_class_check(kernel_impl) -> None:
    """Taichi asks, for every ti.func and ti.kernel it decorates, whether the decorator runs in a class body: it
    reads the source line of the frame there with inspect.getframeinfo, whose inspect.getmodule scans every loaded
    module each time (95 decorators of Taichi's and ours in a `slam` start-up: a fifth of its import time,
    measured). The same line, read from linecache directly, answers the same."""
    import linecache

    patterns = kernel_impl._KERNEL_CLASS_STACKFRAME_STMT_RES

    def _inside_class(level_of_class_stackframe):
        try:
            frame = sys._getframe(level_of_class_stackframe)
            line = linecache.getline(frame.f_code.co_filename, frame.f_lineno, frame.f_globals).strip()
        except ValueError:  # no frame that deep
            return False
        return any(pattern.match(line) for pattern in patterns)

    kernel_impl._inside_class = _inside_class


with _stdout_to_stderr(), (_engine_import_trimmed() if ENGINE == "taichi" else contextlib.nullcontext()):
    try:
        ti = importlib.import_module(ENGINE)
    except ImportError as exc:
        if exc.name != ENGINE:
            raise
        from ti_cmax.errors import InputError

        extra = " (pip install 'ti-cmax[quadrants]')" if ENGINE == "quadrants" else ""
        raise InputError(f"kernel engine {ENGINE} is not installed{extra}") from None

if not REQUIRED_VERSION[0] <= tuple(ti.__version__) < REQUIRED_VERSION[1]:  # pragma: no cover - install problem
    low, high = (".".join(map(str, v)) for v in REQUIRED_VERSION)
    raise ImportError(f"ti_cmax needs {ENGINE}>={low},<{high}, found {'.'.join(map(str, ti.__version__))}")


def _short_pos_info(ctx, node) -> str:
    """Where a Taichi AST node is (file, line, function), without the caret drawing of the source line.

    Taichi builds this message for every AST node of every kernel in every process, also when the compiled
    kernel comes from the offline cache; with the drawing (a TextWrapper per node) it cost about a third of the
    kernel preparation on a warm cache (measured CPU seconds: back-end 2.0 -> 1.25, front-end 0.57 -> 0.40).
    Compilation errors still name the file and line."""
    return f'File "{ctx.file}", line {node.lineno + ctx.lineno_offset}, in {ctx.func.func.__name__}:\n'


def _cache_kernel_sources() -> None:
    """Taichi 1.7 reads a function's source again (inspect.getsourcelines: tokenises the whole file) at every
    call site of a ti.func while it transforms a kernel: 549 times per `slam` run, ~0.15 CPU s of the start-up
    (measured). The source cannot change during a run, so read it once per function."""
    from taichi.lang import kernel_impl

    read = kernel_impl.getsourcelines

    @functools.lru_cache(maxsize=None)
    def cached(obj):
        lines, start = read(obj)
        return tuple(lines), start

    def getsourcelines(obj):
        lines, start = cached(obj)
        return list(lines), start

    kernel_impl.getsourcelines = getsourcelines


if ENGINE == "taichi":  # quadrants neither draws the caret per node nor reads sources again per call site
    if os.environ.get("TI_CMAX_FULL_TAICHI_ERRORS", "") in ("", "0"):
        from taichi.lang.ast import ast_transformer_utils as _ast_utils

        _ast_utils.ASTTransformerContext.get_pos_info = _short_pos_info
    _cache_kernel_sources()

_state = {"initialized": False, "threads": None, "chosen": False}


def initialized() -> bool:
    """Whether this process has initialized the engine (ensure_init)."""
    return _state["initialized"]


def set_num_threads(n: int | None) -> None:
    """Choose the CPU thread count; must be called before the first kernel launch."""
    if _state["initialized"] and n != _state["threads"]:
        raise RuntimeError("Taichi is already initialized; set the thread count before the first kernel")
    _state["threads"] = n
    _state["chosen"] = n is not None


def share_cores(processes: int) -> None:
    """Before the first kernel: this process runs beside ``processes - 1`` others (a back-end worker), so it takes
    its share of the cores, unless a thread count was chosen (set_num_threads / --threads, TI_CMAX_THREADS).
    Oversubscribed Taichi thread pools wait for descheduled threads at every parallel loop: `slam --parallel` on 2
    cores took 8.0-12.5 s with 2 threads per process, 7.4-7.8 s with 1 (3 M events, load 5)."""
    if _state["initialized"] or _state["threads"] or os.environ.get("TI_CMAX_THREADS"):
        return
    _state["threads"] = max(1, available_cores() // max(1, int(processes)))


def threads_chosen() -> bool:
    """Whether the user chose the thread count (set_num_threads / --threads, or TI_CMAX_THREADS)."""
    return bool(_state["chosen"] or os.environ.get("TI_CMAX_THREADS"))


def available_cores() -> int:
    """Cores this process may run on: its CPU affinity (a container's or taskset's cpuset), else os.cpu_count()."""
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):  # not on Linux
        return os.cpu_count() or 1


def num_threads() -> int:
    if _state["threads"]:
        return int(_state["threads"])
    env = os.environ.get("TI_CMAX_THREADS")
    return int(env) if env else available_cores()


def ensure_init() -> None:
    """Initialize Taichi once: CPU arch, offline cache, quiet log, chosen thread count."""
    if _state["initialized"]:
        return
    threads = num_threads()
    # discarded: the engine's "[Taichi] Starting on arch=x64" line broke into the progress bars (errors still raise)
    with _stdout_to_stderr(discard=True):
        ti.init(
            arch=ti.cpu,
            offline_cache=True,
            cpu_max_num_threads=threads,
            log_level=ti.WARN,
            debug=False,
            kernel_profiler=os.environ.get("TI_CMAX_KERNEL_PROFILER", "") not in ("", "0"),
            fast_math=os.environ.get("TI_CMAX_FAST_MATH", "1") != "0",
        )
    _state["initialized"] = True
    _state["threads"] = threads
    from .blur import set_blur_threads

    set_blur_threads(threads)
    limit_blas_threads()


def shutdown() -> None:
    """Finalize the engine's program if this process initialized it: its offline cache writes the kernels compiled
    here to disk, so that later processes load them. The engine does this when the interpreter tears down, which a
    multiprocessing worker (it ends with os._exit) and the command line's quick exit skip: without it a back-end
    worker compiled its kernels again in every run. Only at the end of a process: kernels bound before
    (BoundLaunch) refer to the finalized program."""
    if not _state["initialized"]:
        return
    _state["initialized"] = False
    ti.reset()


def limit_blas_threads() -> None:
    """numpy's and scipy's BLAS (OpenBLAS) to one thread in a process that runs the kernels, unless the user set
    OPENBLAS_NUM_THREADS: the math runs in Taichi and OpenCV, BLAS only sees small products (spline fits, BFGS, a
    few sums), and after a call its idle threads spin on the other core beside the kernels (~0.1 CPU s per thread
    during start-up; 3.4 CPU s per 4 s run when the settle step once summed squares with a BLAS dot; offline
    `slam --parallel` at 2 M ev/s with the variable set, three interleaved pairs: process CPU 12.0-14.2 -> 11.3-12.1
    s, system time 0.75-0.94 -> 0.54-0.63 s). The variable (set when ti_cmax is imported) also reaches BLAS
    libraries loaded later and the back-end worker process."""
    if os.environ.get("OPENBLAS_NUM_THREADS") != "1":  # importing ti_cmax set it to 1 unless the user chose
        return
    if not sys.modules["ti_cmax"]._NUMPY_BEFORE_BLAS_LIMIT:  # numpy's BLAS read the variable when it loaded
        return  # (threadpoolctl's scan of the loaded libraries costs ~0.04 CPU s of each process's start-up)
    from threadpoolctl import threadpool_limits

    threadpool_limits(1, user_api="blas")  # the BLAS libraries already loaded (numpy's)


# BoundLaunch's view of the engine's internals: the same steps under other names (taichi: a tuple slot per argument,
# the compiled kernels by index; quadrants: an int slot, the materialized kernels by key, a CompileResult)
if ENGINE == "taichi":
    _PARAMETERS, _CXX_KERNELS = "arguments", "compiled_kernels"

    def _slot(i: int):
        return (i,)

    def _prepare(kernel, impl) -> None:
        pass
else:
    _PARAMETERS, _CXX_KERNELS = "arg_metas", "materialized_kernels"

    def _slot(i: int):
        return i

    def _prepare(kernel, impl) -> None:
        """What quadrants' Kernel.__call__ sets before ensure_compiled."""
        kernel.raise_on_templated_floats = impl.current_cfg().raise_on_templated_floats


class BoundLaunch:
    """A kernel bound once to its arguments (C-contiguous numpy arrays of the annotated dtype, ints, floats); each
    call launches the compiled kernel on them again.

    Why: Taichi 1.7.4's kernel call spends ~60 us of Python per launch with three numpy arguments (per argument:
    type checks, pointer and shape extraction; then the compiled kernel's lookup by argument features and a new
    launch context), quadrants' ~30 us, a bound launch ~2 us (measured on these machines). The front-end launches
    two kernels per evaluation, ~1 ms each on a DAVIS240C packet. The arrays are read and written in place, so the
    caller keeps them alive and unreallocated while bound, and rebinds to change one (``set_array``: a new packet).
    Binding compiles the kernel when a call would (same compiled kernel, offline cache). Uses the engine's internals
    (``Kernel.ensure_compiled``, ``make_launch_context``, ``Program.launch_kernel``): hence the engine versions
    pinned above."""

    def __init__(self, kernel, *args):
        self._kernel = kernel._primal  # the Kernel behind the @ti.kernel function
        self.bind(*args)

    def bind(self, *args) -> None:
        impl = importlib.import_module(f"{ENGINE}.lang.impl")
        kernel = self._kernel
        parameters = getattr(kernel, _PARAMETERS)
        if len(args) != len(parameters):
            raise TypeError(f"{kernel.func.__name__} takes {len(parameters)} arguments, got {len(args)}")
        _prepare(kernel, impl)
        t_kernel = getattr(kernel, _CXX_KERNELS)[kernel.ensure_compiled(*args)]
        prog = impl.get_runtime().prog
        ctx = t_kernel.make_launch_context()
        for i, (value, parameter) in enumerate(zip(args, parameters)):
            if isinstance(value, np.ndarray):
                element = getattr(parameter.annotation, "dtype", None)
                if not value.flags.c_contiguous or getattr(element, "ndim", 0):  # vector elements: not handled
                    raise TypeError(f"argument {i} of {kernel.func.__name__}: a C-contiguous array of scalars")
                ctx.set_arg_external_array_with_shape(_slot(i), int(value.ctypes.data), value.nbytes,
                                                      list(value.shape), 0)
            elif isinstance(value, (bool, int, np.integer)):
                ctx.set_arg_int(_slot(i), int(value))
            elif isinstance(value, (float, np.floating)):
                ctx.set_arg_float(_slot(i), float(value))
            else:
                raise TypeError(f"argument {i} of {kernel.func.__name__}: {type(value).__name__} cannot be bound")
        compiled = prog.compile_kernel(prog.config(), prog.get_device_caps(), t_kernel)
        self._compiled = getattr(compiled, "compiled_kernel_data", compiled)  # quadrants: inside a CompileResult
        self._prog, self._ctx, self._args = prog, ctx, args  # the arguments stay referenced while bound

    def set_array(self, index: int, value: np.ndarray) -> None:
        """Rebind argument ``index`` to another array of the same dtype and dimensions (the same compiled kernel):
        a few us instead of a whole ``bind``."""
        old = self._args[index]
        if (not isinstance(value, np.ndarray) or value.dtype != old.dtype or value.ndim != old.ndim
                or not value.flags.c_contiguous):
            raise TypeError(f"argument {index}: a C-contiguous {old.dtype} array of {old.ndim} dimensions")
        self._ctx.set_arg_external_array_with_shape(_slot(index), int(value.ctypes.data), value.nbytes,
                                                    list(value.shape), 0)
        self._args = self._args[:index] + (value,) + self._args[index + 1:]

    def __call__(self) -> None:
        self._prog.launch_kernel(self._compiled, self._ctx)


# Taichi 1.7.4 runs a CPU range-for of N iterations as tasks of max(512, ceil(N / threads)) consecutive
# iterations, one thread each (measured: tests/kernels/test_iwe.py). A loop of <= 512 iterations (2 vote parts, a
# few hundred rows) therefore runs on one thread. Voting in P parts, each into its own image copy with plain
# load/add/store, loops over PART_TASK iterations per part: with P <= threads, or P a multiple of threads, every
# task holds whole parts, so one thread writes each copy, in event order (deterministic).
PART_TASK = 512


def check_parts(parts: int) -> int:
    """``parts`` if every CPU task of a P x PART_TASK loop holds whole parts (see above), else ValueError."""
    threads = num_threads()
    if parts > threads and parts % threads:
        raise ValueError(f"parts={parts} must be at most the thread count ({threads}) or a multiple of it")
    return parts


@ti.func
def part_slice(it, n, parts):
    """Iteration ``it`` of a ``range(parts * PART_TASK)`` loop over n items: (part, first item, end item); part p
    covers items [p ceil(n/P), (p+1) ceil(n/P)), in PART_TASK consecutive slices."""
    chunk = (n + parts - 1) // parts
    sub = (chunk + PART_TASK - 1) // PART_TASK
    part = it // PART_TASK
    k0 = part * chunk + (it % PART_TASK) * sub
    k1 = ti.min(ti.min(n, (part + 1) * chunk), k0 + sub)
    return part, k0, k1


@ti.func
def even_slice(it, n, tasks):
    """Iteration ``it`` of a ``range(tasks)`` loop over n independent items (rows, batches): items [it n / tasks,
    (it + 1) n / tasks), so that a loop of few items still makes one task per thread (see PART_TASK); 64-bit
    products (n x tasks passes 2^31 from 2 M items on 1024 tasks)."""
    lo = ti.cast(ti.cast(it, ti.i64) * n // tasks, ti.i32)
    hi = ti.cast(ti.cast(it + 1, ti.i64) * n // tasks, ti.i32)
    return lo, hi


__all__ = ["ti", "BoundLaunch", "ensure_init", "initialized", "shutdown", "set_num_threads", "num_threads",
           "threads_chosen", "share_cores", "available_cores", "PART_TASK", "check_parts", "part_slice", "even_slice"]

