"""The back-end as online SLAM talks to it: one interface (``OnlineBackend``), implemented in this process by
``BackendRunner`` and in a worker process by ``worker.WorkerBackend``.

The runner feeds event chunks (downsampled, as bearings) and the front-end's integrated poses to a
``SlidingWindowBackend``, which it creates at the first event with loop closure attached when configured, runs every
window that is ready, and times them.
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Callable, Iterable, Iterator, Protocol

import numpy as np

from ti_cmax.camera import Camera
from ti_cmax.config import SlamConfig
from ti_cmax.events import Events
from ti_cmax.spline import SO3Spline
from ti_cmax.trajectory import Trajectory

from .backend import SlidingWindowBackend, WindowReport, event_buffer
from .backend_policies import KEPT_INITIALISATION, REFITTED, WindowBudget
from .frontend import every_qth
from .loop_closure import LoopCloser


@dataclass
class BackendOutcome:
    """What the back-end hands over at the end of the stream."""

    report: dict  # report.json's "backend" block
    spline: SO3Spline | None
    map: np.ndarray  # (h, w) float32 panoramic map I_G
    windows: list
    trajectory: Trajectory  # the spline sampled at output.trajectory_rate
    loops: list | None = None  # loop closure's candidates (report.json "loops"), if it ran
    process: dict | None = None  # a worker process's own figures (report.json "backend_process")


class OnlineBackend(Protocol):
    """The back-end of ``OnlineSlam``: wherever it runs, the same calls in the same order give the same result.
    Methods that complete windows return their reports, for the caller's ``on_window``."""

    started: bool  # an event was pushed (the back-end exists)
    seconds: float  # steady-state wall seconds in the back-end's windows
    cpu_seconds: float  # CPU seconds of this process in them (0 with a worker)
    blocked_seconds: float  # wall seconds the caller waited for a worker (0 in-process)

    def compile(self) -> float: ...

    def push_events(self, chunk: Events) -> None: ...

    def advance(self, t: float, rotation: np.ndarray, moving: bool,
                budget: Callable[[], WindowBudget]) -> Iterator[WindowReport]: ...

    def poll(self, t_last: float | None) -> Iterator[WindowReport]: ...

    def pose(self, t) -> np.ndarray: ...

    def refined_until(self) -> float | None: ...

    def map(self) -> np.ndarray | None: ...

    def finish(self, budget: WindowBudget) -> tuple[list[WindowReport], BackendOutcome]: ...

    def wait_ready(self) -> None: ...

    def prepare(self, rate: float) -> None: ...

    def abort(self) -> None: ...


def backend_report(backend: SlidingWindowBackend, wall: float) -> dict:
    """report.json's "backend" block."""
    optimized = [w for w in backend.windows if w.optimized]
    in_optimized = sum(w.num_events for w in optimized)
    observer = backend.observer.summary()
    return {
        "windows": len(backend.windows),
        "windows_optimized": len(optimized),
        # windows over which the front-end measured no motion (backend_skip_still_windows): no BA
        "windows_still": sum(1 for w in backend.windows if w.still),
        # false maxima: the window kept its initialisation (a correction beyond backend_max_correction, or an
        # optimum that failed the check and whose refit did too), or its refit's optimum replaced the first one
        "windows_rejected": sum(1 for w in backend.windows if w.rejected),
        "windows_refitted": sum(1 for w in backend.windows if w.refitted),
        # the optimum departed beyond the check's bound and a local refit found the same maximum (kept)
        "windows_confirmed_by_refit": sum(1 for w in backend.windows if w.confirmed),
        "false_maxima": [{"t_start": w.t_start, "t_end": w.t_end, "reason": w.false_maximum,
                          "outcome": REFITTED if w.refitted else KEPT_INITIALISATION}
                         for w in backend.windows if w.false_maximum is not None],
        "mean_iterations": float(np.mean([w.iterations for w in optimized])) if optimized else 0.0,
        "mean_evaluations": float(np.mean([w.evaluations for w in optimized])) if optimized else 0.0,
        "events_settled": int(backend.events_settled),
        "event_window_pairs_optimized": int(backend.events_optimized),
        "max_window_events": int(backend.cfg.backend_max_window_events),
        # of the events in optimized windows, the fraction the BA used (below 1 when windows were sampled)
        "events_used_fraction": (sum(w.events_used for w in optimized) / in_optimized) if in_optimized else 1.0,
        "wall_seconds": wall,
        "us_per_event": wall * 1e6 / backend.events_settled if backend.events_settled else 0.0,
        "map_size": [int(backend.width), int(backend.height)],
        "spline_degree": int(backend.cfg.spline_degree),
        "control_poses": int(backend.spline.num_control) if backend.spline is not None else 0,
        "stages": backend.clock.summary(),  # CPU and wall seconds of fit, ba, settle (and loop)
        **({"loop_closure": observer} if observer is not None else {}),
    }


def compile_backend(config: SlamConfig) -> float:
    """Compile the back-end kernels on a tiny problem so that steady-state timing excludes compilation."""
    from ti_cmax.kernels.gather import BearingGather
    from ti_cmax.kernels.pano import PanoIWE, vote_map

    tic = time.perf_counter()
    b = np.array([[0.0, 0.0, 1.0]] * 4, np.float32)
    w, h = 16, 8
    ctrl = np.stack([np.eye(3)] * (config.backend.spline_degree + 1))
    problem = PanoIWE(b, np.zeros(1, np.int32), np.zeros(1), config.backend.spline_degree, w, h,
                      sigma=config.backend.backend_blur_sigma, batch_size=4,
                      global_blurred=np.ones((h, w), np.float32), global_sums=(float(w * h), float(w * h)), alpha=1.0)
    problem.cost_and_grad(ctrl)
    problem.votes(ctrl)  # the settle's projection (votes only)
    BearingGather(b, 1)(np.zeros(1), np.zeros(1, np.uint16), np.zeros(1, np.uint16), 0, 1, 1, np.zeros(1),
                        np.zeros((3, 1), np.float32), 0)  # the events' way into the window buffer
    vote_map(b, np.eye(3)[None], w, h, batch_size=4, occupancy=(np.zeros(w, np.int32), np.zeros(h, np.int32)))
    return time.perf_counter() - tic


class BackendRunner:
    """The back-end in this process (``OnlineBackend``). ``r_start_of(t0)``: the first pose, given the first event's
    time (the identity online; a given trajectory's pose when refining). ``loop_slice_seconds``: loop verifications in
    slices of at most this many wall seconds per window (LoopCloser; the real-time replay), None: at once."""

    blocked_seconds = 0.0

    def __init__(self, camera: Camera, config: SlamConfig, r_start_of=None,
                 loop_slice_seconds: float | None = None):
        self.camera, self.config = camera, config
        self.r_start_of = r_start_of or (lambda t0: np.eye(3))
        self.loop_slice_seconds = loop_slice_seconds
        self.backend: SlidingWindowBackend | None = None
        self.events_read = 0
        self._gather = None  # BearingGather, bound at the first events
        self._prepared = None  # the back-end's event buffer, when prepared for the stream's rate
        self.seconds = self.cpu_seconds = 0.0

    @property
    def started(self) -> bool:
        return self.backend is not None

    def compile(self) -> float:
        """Compile the kernels and build the camera's bearing table (before the events: a table takes 0.2-0.3 s on
        a distorted HD sensor)."""
        seconds = compile_backend(self.config)
        tic = time.perf_counter()
        # bound once here (a first call binds the kernel to its arrays: ~10 ms)
        self._bearing_gather()(np.zeros(1), np.zeros(1, np.uint16), np.zeros(1, np.uint16), 0, 1, 1, np.zeros(1),
                               np.zeros((3, 1), np.float32), 0)
        if self.config.loop.loop_closure:
            LoopCloser.prepare(self.config.loop, self.loop_slice_seconds)  # before the events, not at the first ones
        return seconds + time.perf_counter() - tic

    def push_events(self, chunk: Events) -> None:
        """Feed a chunk (downsampled by backend_event_sample_rate, as bearings); the first creates the back-end."""
        if len(chunk) == 0:
            return
        if not chunk.has_subpixel_coordinates:
            self._push_pixels(chunk.t, chunk.x, chunk.y, 0, len(chunk))
            return
        self._start(float(chunk.t[0]))
        sub = every_qth(chunk, int(self.config.backend.backend_event_sample_rate), self.events_read)
        self.events_read += len(chunk)
        self.backend.push_events(sub.t, self.camera.bearings(sub.x, sub.y), complete_until=float(chunk.t[-1]))

    def push_ring(self, ring, position: int, n: int, subpixel: bool) -> None:
        """``push_events`` of the ``n`` events at ``position`` of an ``EventRing`` (worker.py), read in place."""
        if subpixel or n == 0:
            with ring.borrow(position, n, subpixel) as chunk:
                self.push_events(chunk)
            return
        with ring.reading(position, n):
            t, x, y, _ = ring.columns(False)
            self._push_pixels(t, x, y, position % ring.capacity, n)

    def _start(self, t0: float) -> None:
        """Create the back-end at the first event (time ``t0``)."""
        if self.backend is None:
            self.backend = SlidingWindowBackend(self.config.backend, t0, self.r_start_of(t0), events=self._prepared)
            self._prepared = None
            if self.config.loop.loop_closure:  # loop closure on revisits (pipelines/loop_closure.py)
                self.backend.attach(LoopCloser(self.config.loop, self.backend, self.loop_slice_seconds))

    def _bearing_gather(self):
        """The kernel that writes events into the back-end's buffer (``kernels/gather.py``), bound to the camera's
        bearing table (its separable form for an undistorted camera)."""
        if self._gather is None:
            from ti_cmax.kernels.gather import BearingGather  # loaded with the back-end

            cam = self.camera
            self._gather = BearingGather(cam.bearing_lut, cam.width) if cam.has_distortion else \
                BearingGather(cam.separable_bearing_lut, cam.width, separable=True)
        return self._gather

    def _push_pixels(self, t: np.ndarray, x: np.ndarray, y: np.ndarray, start: int, n: int) -> None:
        """``push_events`` of the ``n`` (> 0) integer-pixel events from row ``start`` of the columns t, x, y (rows
        wrap around at their end): every q-th by its index in the stream (as ``every_qth``), gathered by one kernel
        into the back-end's buffer."""
        rows = len(t)
        self._start(float(t[start % rows]))
        q = int(self.config.backend.backend_event_sample_rate)
        first = (-self.events_read) % q
        count = max(0, -(-(n - first) // q))
        self.events_read += n
        gather = self._bearing_gather()
        self.backend.push_written(count, lambda times, bearings, row: gather(
            t, x, y, start + first, q, count, times, bearings, row), complete_until=float(t[(start + n - 1) % rows]))

    def feed(self, chunks: Iterable[Events]) -> Iterator[Events]:
        """Pass chunks through unchanged while pushing them (the offline refinement's reading loop)."""
        for chunk in chunks:
            if len(chunk):
                self.push_events(chunk)
                yield chunk

    def advance(self, t: float, rotation: np.ndarray, moving: bool,
                budget: Callable[[], WindowBudget]) -> Iterator[WindowReport]:
        """Add a source pose and run every window it completes (each with the budget in force when it starts)."""
        backend = self.backend
        backend.push_source_poses([t], rotation[None], [moving])
        while backend.ready():
            tic, cpu = time.perf_counter(), time.process_time()
            report = backend.step(budget())
            self.seconds += time.perf_counter() - tic
            self.cpu_seconds += time.process_time() - cpu
            yield report

    def poll(self, t_last: float | None = None) -> Iterator[WindowReport]:
        """Windows completed elsewhere meanwhile: none (every window runs in ``advance``)."""
        return iter(())

    def pose(self, t) -> np.ndarray:
        if self.backend is None:
            return np.broadcast_to(np.eye(3), (np.size(t), 3, 3)).copy()
        return self.backend.pose_at(t)

    def refined_until(self) -> float | None:
        return None if self.backend is None else self.backend.refined_until

    def map(self) -> np.ndarray | None:
        """A copy of the map of the events settled so far (rebuilt first after a loop correction)."""
        return None if self.backend is None else self.backend.refresh_map().raw.copy()

    def finish(self, budget: WindowBudget) -> tuple[list[WindowReport], BackendOutcome]:
        """The end of the stream: the windows left, and the outcome."""
        backend = self.backend
        done = len(backend.windows)
        tic, cpu = time.perf_counter(), time.process_time()
        backend.finish(budget)
        self.seconds += time.perf_counter() - tic
        self.cpu_seconds += time.process_time() - cpu
        return backend.windows[done:], self.outcome()

    def outcome(self) -> BackendOutcome:
        backend = self.backend
        return BackendOutcome(backend_report(backend, self.seconds), backend.spline, backend.map.raw,
                              backend.windows, backend.trajectory(self.config.output.trajectory_rate),
                              backend.observer.loops)

    def wait_ready(self) -> None:
        """Nothing to wait for: the kernels were compiled by ``compile``."""

    def prepare(self, rate: float) -> None:
        """Before the first events: the back-end's event buffer prepared for ``rate`` events/s (its memory written
        once now, ``_Buffer.prepare``). A real-time replay calls it before its clock starts."""
        if self.backend is None:
            self._prepared = event_buffer(self.config.backend, rate)

    def abort(self) -> None:
        """Nothing runs beside the caller."""
