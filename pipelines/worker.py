"""The back-end in a worker process (paper Fig. 3: the front-end and the back-end run at the same time).

``WorkerBackend`` is the ``online_backend.OnlineBackend`` of ``OnlineSlam`` when the back-end runs beside it: it sends
event chunks and source poses to a spawned process that runs a ``BackendRunner`` on them, in the same order as in one
process, so the results are the same (bitwise with one Taichi thread per process). The events go through an
``EventRing`` in shared memory (one copy in, one copy out; the message says where they are), not through pickles: at
VGA rates a pickle, its pipe writes and the worker's unpickling cost more than the rest of the hand-over. Each pose
message carries the real-time budget in force when it was sent. A mirror back-end follows the worker's refined windows
(``SlidingWindowBackend.follow``) to answer pose queries at once. A thread would not help: Taichi kernel launches
hold the GIL.
"""
from __future__ import annotations

import contextlib
import os
import queue
import sys
import time
from typing import Callable, Iterator

import numpy as np

from ti_cmax import timeline
from ti_cmax.camera import Camera
from ti_cmax.config import SlamConfig
from ti_cmax.errors import UNGUARDED_MAIN, UNGUARDED_MAIN_EXIT, WorkerLost, exit_if_spawn_bootstrapping
from ti_cmax.events import Events
from ti_cmax.outputs import peak_rss_mb

from .backend import SlidingWindowBackend, StageClock, WindowReport
from .backend_policies import WindowBudget
from .online_backend import BackendOutcome, BackendRunner

# sensors up to this many pixels get a back-end worker by default (default_backend_process): VGA-class and below
WORKER_MAX_SENSOR_PIXELS = 500_000
# events the shared ring holds per sensor pixel, within these bounds: about 0.3 s of a VGA sensor at 12 M events/s (the
# events sent while the worker runs a window's BA); 17 bytes per event
RING_EVENTS_PER_PIXEL = 16
RING_EVENTS_RANGE = (1 << 18, 1 << 22)
RING_WAIT = 0.0005  # seconds between looks at the worker's progress while the ring is full


def ring_capacity(camera: Camera) -> int:
    """Events of the ``EventRing`` between this process and the worker, for ``camera``'s sensor."""
    lo, hi = RING_EVENTS_RANGE
    return int(min(hi, max(lo, RING_EVENTS_PER_PIXEL * camera.width * camera.height)))


class EventRing:
    """Events in a ring of shared memory, one writer (the main process) and one reader (the worker): the writer
    copies a chunk in and sends its position in a message; the reader copies it out and then advances the shared
    count of events read, which frees their room. Columns: t float64, x and y (uint16, or float32 for sub-pixel
    coordinates: 4 bytes each, the message says which), p int8. ``buffer``: shared memory of ``nbytes(capacity)``
    bytes (``multiprocessing.RawArray``: it passes to a forked or a spawned worker and is freed with both)."""

    HEADER = 64  # the count of events read (int64), alone on its cache line

    def __init__(self, buffer, capacity: int):
        self.capacity = int(capacity)
        raw = np.frombuffer(buffer, np.uint8)
        if len(raw) < self.nbytes(capacity):
            raise ValueError(f"ring buffer of {len(raw)} bytes, {self.nbytes(capacity)} needed")
        cap, h = self.capacity, self.HEADER
        self._read = raw[:8].view(np.int64)
        self.t = raw[h:h + 8 * cap].view(np.float64)
        self._xy = raw[h + 8 * cap:h + 16 * cap]  # x then y, 4 bytes per event each
        self.p = raw[h + 16 * cap:h + 17 * cap].view(np.int8)
        self.written = 0  # events written (the writer's count)

    @classmethod
    def nbytes(cls, capacity: int) -> int:
        return cls.HEADER + 17 * int(capacity)

    @property
    def read(self) -> int:
        """Events the reader has copied out (shared)."""
        return int(self._read[0])

    def free(self) -> int:
        return self.capacity - (self.written - self.read)

    def _columns(self, subpixel: bool):
        kind = np.float32 if subpixel else np.uint16
        half = 4 * self.capacity
        return (self.t, self._xy[:half].view(kind)[:self.capacity], self._xy[half:].view(kind)[:self.capacity],
                self.p)

    def _spans(self, position: int, n: int):
        start = position % self.capacity
        first = min(n, self.capacity - start)
        return ((start, start + first, 0, first),) + (((0, n - first, first, n),) if first < n else ())

    def put(self, events: Events) -> int:
        """Copy ``events`` in (the caller made room: ``free() >= len(events)``); return their position."""
        n = len(events)
        if n > self.free():
            raise ValueError(f"{n} events do not fit the ring ({self.free()} free)")
        position = self.written
        columns = self._columns(events.has_subpixel_coordinates)
        for (r0, r1, e0, e1) in self._spans(position, n):
            for ring, field in zip(columns, (events.t, events.x, events.y, events.p)):
                ring[r0:r1] = field[e0:e1]
        self.written += n
        return position

    def take(self, position: int, n: int, subpixel: bool) -> Events:
        """Copies of the ``n`` events at ``position`` (in the order they were put); their room is free after."""
        with self.borrow(position, n, subpixel) as events:
            return Events(*(np.array(getattr(events, f)) for f in ("t", "x", "y", "p")))

    @contextlib.contextmanager
    def borrow(self, position: int, n: int, subpixel: bool):
        """The ``n`` events at ``position`` for the ``with`` block: views of the ring (a copy where they wrap
        around), freed for the writer at its end, so the block must keep no reference to them (the back-end's window
        buffer copies what it keeps: one copy fewer per event than ``take``)."""
        spans = self._spans(position, n)
        with self.reading(position, n):
            yield Events(*[column[spans[0][0]:spans[0][1]] if len(spans) == 1 else
                           np.concatenate([column[r0:r1] for r0, r1, _, _ in spans])
                           for column in self._columns(subpixel)])

    @contextlib.contextmanager
    def reading(self, position: int, n: int):
        """The ``with`` block reads the ``n`` events at ``position`` in place (``columns``, from row ``position``
        modulo the capacity, wrapping around); their room is freed for the writer at its end."""
        if position != self.read:
            raise RuntimeError(f"ring read out of order: events at {position}, {self.read} read so far")
        try:
            yield
        finally:
            self._read[0] = position + n

    def columns(self, subpixel: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The ring's t, x, y, p arrays (``capacity`` rows each; x and y float32 for sub-pixel coordinates)."""
        return self._columns(subpixel)


class RingWriter:
    """The writing end of an ``EventRing``: ``write`` copies events in (in pieces of at most half the ring), waiting
    while it lacks room; ``flush`` announces the events written since the last announcement in one message,
    ("events", position, count, sub-pixel), through ``send``. Before waiting it announces what it wrote (the reader
    frees room only for events it knows of); ``check_alive()`` raises when the reader has ended."""

    def __init__(self, ring: EventRing, send: Callable[[tuple], None], check_alive: Callable[[], None]):
        self.ring, self.send, self.check_alive = ring, send, check_alive
        self._unsent: list | None = None  # [position, count, sub-pixel] of events written, not announced yet
        self.blocked_seconds = 0.0

    def write(self, events: Events) -> None:
        ring, subpixel = self.ring, events.has_subpixel_coordinates
        piece = max(1, ring.capacity // 2)
        for i in range(0, len(events), piece):
            part = events[i:i + piece] if len(events) > piece else events
            if self._unsent is not None and self._unsent[2] != subpixel:
                self.flush()
            if ring.free() < len(part):
                self.flush()
                self._wait_for_room(len(part))
            position = ring.put(part)
            if self._unsent is None:
                self._unsent = [position, 0, subpixel]
            self._unsent[1] += len(part)

    def flush(self) -> None:
        if self._unsent is not None:
            position, n, subpixel = self._unsent
            self._unsent = None
            self.send(("events", position, n, subpixel))

    def _wait_for_room(self, n: int) -> None:
        """Short sleeps until the reader has taken enough (it takes every event announced before its next window)."""
        tic = time.perf_counter()
        while self.ring.free() < n:
            self.check_alive()
            time.sleep(RING_WAIT)
        self.blocked_seconds += time.perf_counter() - tic


def default_backend_process(camera: Camera) -> bool:
    """Whether ``ti-cmax slam`` (and the demo) run the back-end in a worker process when neither --parallel nor
    --sequential is given: when this process may run on 2 or more cores (its CPU affinity), the sensor has at most
    ``WORKER_MAX_SENSOR_PIXELS`` pixels (on larger sensors the back-end's kernels use the cores well by themselves,
    and a second process holds more memory) and the platform has working semaphores (multiprocessing's queues need
    them). A run then costs about the slower of the two processes instead of their sum. The Python API stays in one
    process unless asked: a worker process needs the caller's main module to be importable (spawn)."""
    from ti_cmax.kernels import runtime

    if runtime.available_cores() < 2 or camera.width * camera.height > WORKER_MAX_SENSOR_PIXELS:
        return False
    try:
        import multiprocessing.synchronize  # noqa: F401 - raises ImportError without a working sem_open
    except ImportError:
        return False
    return True


class WorkerBackend:
    """``OnlineBackend`` in a worker process. ``queue_size`` bounds the messages in flight (``push`` blocks while
    the worker is that far behind: nothing dropped, no busy waiting); ``max_backlog`` (sensor seconds) also makes
    ``poll`` wait while the events sent run that far ahead of the worker's last window; ``threads``: the worker's
    Taichi threads (default: this process's count)."""

    cpu_seconds = 0.0  # this process spends no CPU in the back-end's windows

    def __init__(self, camera: Camera, config: SlamConfig, queue_size: int = 16, max_backlog: float | None = None,
                 loop_slice_seconds: float | None = None, threads: int | None = None):
        from ti_cmax.kernels import runtime

        runtime.share_cores(2)  # the worker runs beside this process: half the cores each (unless chosen)
        self.config, self.max_backlog = config, max_backlog
        self._process = _BackendProcess(camera, config, queue_size, loop_slice_seconds, threads, ring_capacity(camera))
        self.mirror: SlidingWindowBackend | None = None  # follows the worker's windows (follow), for pose()
        self._reports: list[WindowReport] = []  # windows followed, not handed to the caller yet
        self.seconds = 0.0

    @property
    def started(self) -> bool:
        return self.mirror is not None

    @property
    def blocked_seconds(self) -> float:
        return self._process.blocked_seconds

    def compile(self) -> float:
        """The worker compiles its own kernels meanwhile (``wait_ready``)."""
        return 0.0

    def push_events(self, chunk: Events) -> None:
        if len(chunk) == 0:
            return
        if self.mirror is None:
            self.mirror = SlidingWindowBackend(self.config.backend, float(chunk.t[0]), np.eye(3))
        self._process.write(chunk)  # into the ring now; announced with the next pose (or before waiting)

    def advance(self, t: float, rotation: np.ndarray, moving: bool,
                budget: Callable[[], WindowBudget]) -> Iterator[WindowReport]:
        """Send the pose (every event pushed so far goes before it, as in one process); its windows come in later
        (``poll``)."""
        self.mirror.push_source_poses([t], rotation[None], [moving])
        self._send_events()
        self._process.send(("pose", t, rotation, moving, budget()))
        return iter(())

    def poll(self, t_last: float | None = None) -> Iterator[WindowReport]:
        """The windows the worker completed since the last call; while it runs more than ``max_backlog`` behind
        ``t_last``, wait for its windows."""
        self._receive()
        while self.max_backlog is not None and t_last is not None and \
                t_last - self.refined_until() > self.max_backlog:
            self._send_events()
            tic = time.perf_counter()
            self._receive(until="window")
            self._process.waited_seconds += time.perf_counter() - tic
        reports, self._reports = self._reports, []
        return iter(reports)

    def pose(self, t) -> np.ndarray:
        if self.mirror is None:
            return np.broadcast_to(np.eye(3), (np.size(t), 3, 3)).copy()
        return self.mirror.pose_at(t)

    def refined_until(self) -> float | None:
        return None if self.mirror is None else self.mirror.refined_until

    def map(self) -> np.ndarray | None:
        """A copy of the worker's map once it has handled everything pushed before (this waits for it)."""
        if self.mirror is None:
            return None
        self._send_events()
        self._process.send(("map",))
        return self._receive(until="map")

    def finish(self, budget: WindowBudget) -> tuple[list[WindowReport], BackendOutcome]:
        self._send_events()
        self._process.send(("finish", budget))
        done = self._receive(until="done")
        self._process.stop()
        reports, self._reports = self._reports, []
        self.seconds, self.cpu_seconds = done["seconds"], done["step_cpu_seconds"]
        outcome = done["outcome"]
        if outcome.map is None:  # the worker left it in the shared buffer
            outcome.map = self._process.map_buffer.array()
        outcome.process = {"compile_seconds": done["compile_seconds"], "cpu_seconds": done["cpu_seconds"],
                           "push_blocked_seconds": self._process.blocked_seconds,
                           # of it, waiting for room in the shared ring of events
                           "ring_wait_seconds": self._process.writer.blocked_seconds,
                           "ring_events": self._process.writer.ring.capacity, "peak_rss_mb": done["peak_rss_mb"],
                           "process_cpu_seconds": done["process_cpu_seconds"],
                           "start_method": self._process.start_method,
                           "timeline_seconds": done["timeline_seconds"]}
        return reports, outcome

    def wait_ready(self) -> None:
        """Wait until the worker has prepared its kernels (a live source starts after this)."""
        if not self._process.ready:
            self._receive(until="ready")

    def prepare(self, rate: float) -> None:
        """The worker's ``BackendRunner.prepare`` for ``rate`` events/s, waited for (before a replay's clock)."""
        self._process.send(("prepare", float(rate)))
        self._receive(until="prepared")

    def abort(self) -> None:
        """Stop the worker at once, without its results (Ctrl-C, or a stream without anything to refine)."""
        self._process.cancel()

    def _send_events(self) -> None:
        """Announce the events written to the ring since the last message, as one message (each costs a pipe write
        and a wake-up of the worker; a live source pushes many small chunks)."""
        self._process.flush()

    def _receive(self, until: str | None = None):
        """Follow the worker's windows in the mirror (their reports wait for ``poll`` or ``finish``); with ``until``
        (a message kind) wait for that message and return its content."""
        for kind, *args in self._process.messages(until):
            if kind == "window":
                self.mirror.follow(args[0])
                self._reports.append(args[0].report)
            elif kind == until:
                return args[0]
        return None


def worker_start_method() -> str:
    """How the worker process starts: ``fork`` on Linux while this process has one thread and has not initialized
    the kernel engine, else ``spawn``. A forked worker inherits the modules this process imported (a spawned one
    imports them again: ~0.4 CPU s before its kernel preparation, on the critical path of a run) and needs no
    importable main module; after ``ti.init`` a forked worker would hang, and forking a process with other threads
    can copy a lock another thread holds."""
    import multiprocessing as mp

    from ti_cmax.kernels import runtime

    if not sys.platform.startswith("linux") or "fork" not in mp.get_all_start_methods() or runtime.initialized():
        return "spawn"
    try:
        threads = len(os.listdir("/proc/self/task"))  # also the threads of native libraries
    except OSError:
        return "spawn"
    return "fork" if threads == 1 else "spawn"


class _BackendProcess:
    """The worker process (``worker_start_method``: forked or spawned), connected by a bounded queue of inputs
    (``send`` blocks while it is full: back-pressure, nothing dropped) and a queue of results."""

    def __init__(self, camera: Camera, config: SlamConfig, queue_size: int, loop_slice_seconds: float | None = None,
                 threads: int | None = None, ring_events: int = RING_EVENTS_RANGE[0]):
        import ctypes
        import multiprocessing as mp
        import signal

        from ti_cmax.kernels import runtime

        exit_if_spawn_bootstrapping()  # in a worker re-running an unguarded script: one line, a known exit
        self.start_method = worker_start_method()
        ctx = mp.get_context(self.start_method)
        self.inbox, self.outbox = ctx.Queue(max(1, queue_size)), ctx.Queue()
        self.inbox.cancel_join_thread()  # never hang at exit on a worker that stopped reading (it failed)
        self.waited_seconds = 0.0  # for a full inbox, or the worker's windows
        buffer = ctx.RawArray(ctypes.c_uint8, EventRing.nbytes(ring_events))
        self.writer = RingWriter(EventRing(buffer, ring_events), self.send, self._check_alive)
        self.map_buffer = SharedMap.create(config) if self.start_method == "fork" else None
        self.proc = ctx.Process(target=_backend_worker, daemon=True,
                                args=(camera, config, threads or runtime.num_threads(), self.inbox, self.outbox,
                                      loop_slice_seconds, (buffer, ring_events), self.map_buffer))
        # Ctrl-C is this process's to handle (the CLI: one line, exit 130), but a terminal sends it to the whole
        # process group. Blocked while the worker is spawned, SIGINT stays blocked in it from its first instruction
        # (the mask survives fork and exec), so it prints no traceback; a Ctrl-C meanwhile reaches this process when
        # unblocked
        mask = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT}) if hasattr(signal, "pthread_sigmask") else None
        try:
            sys.stdout.flush()  # a forked worker would write this process's unflushed output again
            sys.stderr.flush()
            self.proc.start()
        finally:
            if mask is not None:
                signal.pthread_sigmask(signal.SIG_SETMASK, mask)
        self.ready = False  # the worker has prepared its kernels

    @property
    def blocked_seconds(self) -> float:
        """Wall seconds this process waited for the worker: a full inbox or ring, or its windows (``waited``)."""
        return self.waited_seconds + self.writer.blocked_seconds

    def write(self, events: Events) -> None:
        self.writer.write(events)

    def flush(self) -> None:
        self.writer.flush()

    def _check_alive(self) -> None:
        """Raise WorkerLost (or the worker's own error) when the worker has ended."""
        if not self.proc.is_alive():
            for _ in self.messages(None):  # raises the worker's error, if it sent one
                pass
            raise WorkerLost(self._ended(""))

    def send(self, message) -> None:
        """Put a message on the inbox, waiting while it is full (1 s timeouts, to notice a worker that ended)."""
        tic = time.perf_counter()
        while True:
            try:
                self.inbox.put(message, timeout=1.0)
                break
            except queue.Full:
                if not self.proc.is_alive():
                    for _ in self.messages(None):  # raises the worker's error, if it sent one
                        pass
                    raise WorkerLost(self._ended("")) from None
        self.waited_seconds += time.perf_counter() - tic

    def _ended(self, what: str) -> str:
        """Why the worker is gone, in one line."""
        if self.proc.exitcode == UNGUARDED_MAIN_EXIT:
            return f"the back-end worker could not start: {UNGUARDED_MAIN}, or pass backend_process=False"
        return f"the back-end process ended{what} (exit {self.proc.exitcode}: killed or out of memory?)"

    def messages(self, until: str | None):
        """Messages ready now; with ``until`` (a message kind: "done", "map") block (1 s timeouts, to notice a dead
        worker) until that message."""
        while True:
            try:
                msg = self.outbox.get(timeout=1.0) if until else self.outbox.get_nowait()
            except queue.Empty:
                if not until:
                    return
                if not self.proc.is_alive():
                    raise WorkerLost(self._ended(" without a result"))
                continue
            if msg[0] == "ready":
                self.ready = True
            if msg[0] == "error":
                self.proc.terminate()
                raise RuntimeError(f"back-end process: {msg[1]}")
            yield msg
            if msg[0] == until:
                return

    def stop(self) -> None:
        self.proc.join(timeout=10)
        if self.proc.is_alive():
            self.proc.terminate()

    def cancel(self) -> None:
        """End a worker that was never told to finish (nothing to wait for)."""
        if self.proc.is_alive():
            self.proc.terminate()
        self.proc.join(timeout=10)


def _next_message(inbox, poll: float = 1.0):
    """The worker's next message; it exits when its parent process has died meanwhile (killed, or out of memory):
    otherwise it would sleep forever, holding the terminal's pipes open."""
    import multiprocessing

    while True:
        try:
            return inbox.get(timeout=poll)
        except queue.Empty:
            parent = multiprocessing.parent_process()
            if parent is not None and not parent.is_alive():
                os._exit(1)


class SharedMap:
    """The final map's way from a forked worker to the main process: memory both share (an anonymous shared mapping
    made before the fork), instead of the result message. Pickled, piped and unpickled, the 8 MB map of a
    DAVIS240C run cost ~0.03-0.05 s between the worker's last window and the outputs."""

    def __init__(self, buffer, shape: tuple[int, int]):
        self.buffer, self.shape = buffer, shape

    @classmethod
    def create(cls, config: SlamConfig) -> SharedMap:
        import mmap

        w, h = config.backend.pano_size
        return cls(mmap.mmap(-1, w * h * np.dtype(np.float32).itemsize), (h, w))

    def array(self) -> np.ndarray:
        """The map in the buffer (a view: the buffer lives while the array does)."""
        return np.frombuffer(self.buffer, np.float32).reshape(self.shape)

    def put(self, image: np.ndarray) -> bool:
        """Copy ``image`` into the buffer; False (nothing copied) when it is not a float32 map of its shape."""
        if image.dtype != np.float32 or image.shape != self.shape:
            return False
        self.array()[...] = image
        return True


def _backend_worker(camera: Camera, config: SlamConfig, threads: int, inbox, outbox,
                    loop_slice_seconds: float | None = None, ring: tuple | None = None,
                    map_buffer: SharedMap | None = None) -> None:
    """The worker process: a ``BackendRunner`` on messages ("events", position, count, sub-pixel: where they are in
    the ``EventRing`` ``ring`` = (buffer, capacity)), ("pose", t, R, moving, budget), ("map",) (send a copy of the
    map) and ("finish", budget). While no message waits it advances the loop closer's
    verification in flight (sliced in real time). The final map goes into ``map_buffer`` when given (forked)."""
    import signal

    from ti_cmax.workers import die_with_parent

    die_with_parent()  # killed with the main process, also on SIGKILL
    timeline.clear()  # forked: the parent's points came along
    timeline.mark("started")
    # forked: the command line's SIGTERM handler came along (it would end the worker as an error); a spawned worker
    # has the default, SIGTERM ends it. SIGINT stays blocked (see _BackendProcess)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    try:
        from ti_cmax import progress
        from ti_cmax.kernels import runtime

        progress.set_quiet(True)  # no bars here, nor Taichi's start-up line (the main process shows its own)
        runtime.set_num_threads(threads)
        cpu0 = time.process_time()
        runner = BackendRunner(camera, config, loop_slice_seconds=loop_slice_seconds)
        compile_s = runner.compile()
        timeline.mark("ready")
        outbox.put(("ready", compile_s))
        _serve(runner, inbox, outbox, {"compile_seconds": compile_s, "cpu0": cpu0}, EventRing(*ring), map_buffer)
    except BaseException as exc:  # noqa: BLE001 - reported to the parent, which raises it
        outbox.put(("error", f"{type(exc).__name__}: {exc}"))
        return
    runtime.shutdown()  # the kernels compiled here go to the offline cache (the worker ends with os._exit)


def _serve(runner: BackendRunner, inbox, outbox, start: dict, ring: EventRing,
           map_buffer: SharedMap | None = None) -> None:
    """The worker's message loop. Per-stage costs beside the back-end's own: receive (waiting for messages and
    unpickling them), events (from the ring to the window buffer as times and bearings), send (the window
    messages)."""
    clock = StageClock()
    last_done, waited = time.perf_counter(), 0.0  # busy_seconds of a window: wall since the last one - waited
    while True:
        observer = runner.backend.observer if runner.backend is not None else None
        while observer is not None and observer.pending() and inbox.empty():  # idle: the work in flight
            with clock("loop_idle"):
                observer.idle_slice()
        tic = time.perf_counter()
        with clock("receive"):
            kind, *args = _next_message(inbox)
        waited += time.perf_counter() - tic
        if kind == "events":
            with clock("events"):
                runner.push_ring(ring, *args)
            continue
        if kind == "map":  # OnlineSlam.map(): a copy of the map of the events settled so far
            outbox.put(("map", runner.map()))
            continue
        if kind == "prepare":  # OnlineSlam.prepare(rate), before the first events
            runner.prepare(*args)
            outbox.put(("prepared", None))
            continue
        new = len(runner.backend.windows)
        if kind == "pose":
            t, rotation, moving, budget = args
            for _ in runner.advance(t, rotation, moving, lambda: budget):
                pass
        else:
            _, outcome = runner.finish(args[0])
        for update in runner.backend.updates(new):
            now = time.perf_counter()
            update.report.busy_seconds, last_done, waited = max(0.0, now - last_done - waited), now, 0.0
            with clock("send"):
                outbox.put(("window", update))
        if kind == "finish":
            outcome.report["worker_stages"] = clock.summary()
            if map_buffer is not None and map_buffer.put(outcome.map):
                outcome.map = None  # the main process reads it from the shared buffer
            timeline.mark("done")
            outbox.put(("done", {"outcome": outcome, "seconds": runner.seconds, "step_cpu_seconds": runner.cpu_seconds,
                                 "timeline_seconds": timeline.points(),
                                 "compile_seconds": start["compile_seconds"],
                                 "cpu_seconds": time.process_time() - start["cpu0"],
                                 "process_cpu_seconds": time.process_time(), "peak_rss_mb": peak_rss_mb()}))
            return
