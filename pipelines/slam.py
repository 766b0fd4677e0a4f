"""CMax-SLAM (paper Fig. 3): front-end and back-end run in time order over one stream of events.

events -> packets around equispaced times -> omega per packet (front-end) -> integrated source poses ->
sliding-window BA on the panoramic IWE (back-end) -> continuous trajectory + panoramic map.

``OnlineSlam`` is the streaming form (push chunks from a live source, ask for poses at any time) and ``run_slam``
a thin wrapper over it: each event chunk is read once, feeds the front-end's slicer and the back-end's window
buffer, and every window is refined as soon as the front-end has covered it, so memory is bounded by the chunk
size plus one window. ``refine`` is the offline BA (Sec. IV-C2): the same back-end initialized from
any given trajectory (another method's output, IMU dead reckoning) instead of the front-end.
"""
from __future__ import annotations

import os
import time
from dataclasses import dataclass, field
from typing import Iterable, Iterator

import numpy as np

from ti_cmax import so3
from ti_cmax.camera import Camera
from ti_cmax.config import SlamConfig, config_to_dict
from ti_cmax.errors import (UNGUARDED_MAIN, UNGUARDED_MAIN_EXIT, InputError, WorkerLost,
                            exit_if_spawn_bootstrapping)
from ti_cmax.events import Events
from ti_cmax.outputs import peak_rss_mb
from ti_cmax.progress import progress
from ti_cmax.spline import SO3Spline
from ti_cmax.trajectory import Trajectory

from .backend import SlidingWindowBackend, StageClock
from .frontend import NO_MOTION_MEASURABLE, FrontendResult, FrontendRunner, Packet, as_chunks, every_qth
from .loop_closure import LoopCloser
from .sensor_defaults import derived_summary, resolve_config


@dataclass
class SlamResult:
    """Outcome of CMax-SLAM or of the offline BA: trajectory, map, front-end output and a report."""

    spline: SO3Spline | None
    trajectory: Trajectory  # the spline sampled at output.trajectory_rate
    map: np.ndarray  # (h, w) float32 panoramic IWE of all settled events (I_G)
    report: dict
    frontend: FrontendResult | None = None
    windows: list = field(default_factory=list)
    realtime_trace: list = field(default_factory=list)  # real-time replay: realtime.TRACE_COLUMNS per window

    def rotation_at(self, times) -> np.ndarray:
        """R_world_from_camera at any times within the trajectory (the spline itself, not the samples)."""
        times = np.atleast_1d(np.asarray(times, dtype=float))
        if self.spline is None:
            return self.trajectory.at(times)
        start, end = self.spline.valid_time_range()
        return self.spline.evaluate(np.clip(times, start, end))


class _BackendFeed:
    """Passes event chunks through unchanged while feeding them (downsampled by backend_event_sample_rate, with
    bearings) to the back-end, which it creates at the first event. Counts the events read."""

    def __init__(self, camera: Camera, config: SlamConfig, r_start_of, loop_slice_seconds: float | None = None):
        self.camera, self.config, self.r_start_of = camera, config, r_start_of
        self.loop_slice_seconds = loop_slice_seconds  # LoopCloser.slice_seconds (None: verify at once)
        self.backend: SlidingWindowBackend | None = None
        self.events_read = 0

    def push(self, chunk: Events) -> None:
        if len(chunk) == 0:
            return
        if self.backend is None:
            t0 = float(chunk.t[0])
            self.backend = SlidingWindowBackend(self.config.backend, t0, self.r_start_of(t0))
            if self.config.loop.loop_closure:  # loop closure on revisits (pipelines/loop_closure.py)
                self.backend.loop = LoopCloser(self.config.loop, self.backend)
                self.backend.loop.slice_seconds = self.loop_slice_seconds
        sub = every_qth(chunk, int(self.config.backend.backend_event_sample_rate), self.events_read)
        self.events_read += len(chunk)
        self.backend.push_events(sub.t, self.camera.bearings(sub.x, sub.y), complete_until=float(chunk.t[-1]))

    def __call__(self, chunks: Iterable[Events]) -> Iterator[Events]:
        for chunk in chunks:
            if len(chunk):
                self.push(chunk)
                yield chunk


def _backend_report(backend: SlidingWindowBackend, wall: float) -> dict:
    optimized = [w for w in backend.windows if w.optimized]
    in_optimized = sum(w.num_events for w in optimized)
    return {
        "windows": len(backend.windows),
        "windows_optimized": len(optimized),
        # windows over which the front-end measured no motion (backend_skip_still_windows): no BA
        "windows_still": sum(1 for w in backend.windows if w.still),
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
        **({"loop_closure": backend.loop.summary()} if backend.loop is not None else {}),
    }


def _compile_backend(config: SlamConfig) -> float:
    """Compile the back-end kernels on a tiny problem so that steady-state timing excludes compilation."""
    from ti_cmax.kernels.pano import PanoIWE, vote_map

    tic = time.perf_counter()
    b = np.array([[0.0, 0.0, 1.0]] * 4, np.float32)
    w, h = 16, 8
    ctrl = np.stack([np.eye(3)] * (config.backend.spline_degree + 1))
    problem = PanoIWE(b, np.zeros(1, np.int32), np.zeros(1), config.backend.spline_degree, w, h,
                      sigma=config.backend.backend_blur_sigma, batch_size=4,
                      global_blurred=np.ones((h, w), np.float32), global_sums=(float(w * h), float(w * h)), alpha=1.0)
    problem.cost_and_grad(ctrl)
    vote_map(b, np.eye(3)[None], w, h, batch_size=4, occupancy=(np.zeros(w, np.int32), np.zeros(h, np.int32)))
    return time.perf_counter() - tic


class OnlineSlam:
    """CMax-SLAM on a live stream: push time-ordered event chunks as they arrive, ask for poses at any time.

    The computation of :func:`run_slam` (a thin wrapper over this class): each chunk feeds the back-end's window
    buffer and the front-end's packet slicer; each packet's omega is integrated into the source poses, and every
    window is refined as soon as the front-end has covered it. Chunks may have any size (a camera driver's
    packets, a ROS message); the results do not depend on it. ``on_window(report)`` is called after every window
    the back-end completes (a :class:`~ti_cmax.pipelines.backend.WindowReport`); ``close()`` ends the stream and
    returns the :class:`SlamResult` that ``run_slam`` returns. The trajectory starts at the identity at the first
    event (the world frame is the first camera frame).

    ``backend_process=True`` runs the back-end in a worker process at the same time as the front-end (paper
    Fig. 3). A thread would not help: Taichi 1.7 kernel launches hold the GIL (measured, see README). Bounded
    queues connect the two; ``push`` blocks while the worker is a full queue behind (no event is dropped, no busy
    waiting). The worker does the same operations in the same order, so results equal the sequential run
    (bitwise with one Taichi thread per process). ``pose`` then uses the refined spline the worker last sent;
    ``max_backlog`` (sensor seconds) also makes ``push`` wait while it runs that far ahead of the worker's last window.

    ``degrade`` (used by the real-time replay, pipelines/realtime.py) skips front-end packets and samples or skips
    the BA from then on; by default nothing is degraded.
    """

    def __init__(self, camera: Camera, config: SlamConfig = SlamConfig(), *, on_window=None,
                 backend_process: bool = False, queue_size: int = 16, max_backlog: float | None = None,
                 loop_slice_seconds: float | None = None, worker_threads: int | None = None):
        self._wall0 = time.perf_counter()
        if backend_process:
            from ti_cmax.kernels import runtime

            runtime.share_cores(2)  # the worker runs beside this process: half the cores each (unless chosen)
        self.derived = derived_summary(config, camera)
        self.config = config = resolve_config(config, camera)
        self.on_window = on_window
        self.runner = FrontendRunner(camera, config.frontend)
        self._packet_events = self.runner.slicer.n  # N of the resolved config (degrade's input thinning divides it)
        # loop_slice_seconds: loop verifications in slices of at most this many wall seconds per window (and in the
        # worker's idle time) instead of at once (LoopCloser.slice_seconds; the real-time replay)
        # worker_threads: the worker's Taichi threads (default: this process's count)
        self._worker = _BackendProcess(camera, config, queue_size, loop_slice_seconds, worker_threads) \
            if backend_process else None
        cpu0 = time.process_time()
        self.compile_seconds = self.runner.compile() + (0.0 if backend_process else _compile_backend(config))
        # what the process paid before the first event: imports, ti.init, kernel preparation (CPU seconds, which
        # a loaded machine does not inflate, unlike wall time); the worker's own start-up runs meanwhile
        self.startup = {"compile_seconds": self.compile_seconds,
                        "compile_cpu_seconds": time.process_time() - cpu0,
                        "process_cpu_seconds": time.process_time()}
        # sequential: the back-end itself; with a worker: a shadow fed with the source poses and the worker's
        # refined splines, for pose() only (it never refines)
        self._feed = _BackendFeed(camera, config, lambda t0: np.eye(3), loop_slice_seconds)
        self._q_front = int(config.frontend.frontend_event_sample_rate)
        self._r_src = np.eye(3)
        self._t_prev: float | None = None
        self._w_prev: np.ndarray | None = None
        self.t_last: float | None = None  # time of the last event pushed
        self.events_read = 0
        self.backend_seconds = 0.0  # steady-state time in the back-end (windows), callbacks excluded
        self.backend_cpu_seconds = 0.0  # CPU time of this process in the back-end's windows (0 with a worker)
        # real-time degradation (``degrade``, set by pipelines/realtime.py): the front-end processes 1 of
        # frontend_keep packets (the others are skipped: integration goes on from the last processed one)
        self.frontend_keep = 1
        self._ba_cap: int | None = None  # the back-end's ba_cap and ba_every (see SlidingWindowBackend)
        self._ba_every = 1
        self._ba_budget: float | None = None
        self.packets_seen = self.packets_skipped = 0
        self._result: SlamResult | None = None
        # with a worker: push() also waits while the events sent run more than this many sensor seconds ahead of
        # the worker's last window (the queue's bound in messages is none in time when chunks are large)
        self.max_backlog = max_backlog
        self._to_send: list[Events] = []  # with a worker: chunks not yet sent (see _send_events)

    # ---- input ---------------------------------------------------------------------------------------------------
    def push(self, events: Events) -> None:
        """Process a time-ordered chunk (continuing the previous ones): every packet and window it completes."""
        if self._result is not None:
            raise RuntimeError("push() after close()")
        if not isinstance(events, Events):
            raise InputError(f"expected Events chunks, got {type(events).__name__}")
        if len(events) == 0:
            return
        self.runner.check(events)  # times, pixels and pauses (one clear InputError)
        offset = self.events_read
        if self._worker is None:
            self._feed.push(events)
            self._apply_degradation(self._feed.backend)
        else:
            if self._feed.backend is None:
                self._feed.backend = SlidingWindowBackend(self.config.backend, float(events.t[0]), np.eye(3))
            self._to_send.append(events)  # sent with the next pose (or before waiting): fewer, larger messages
        self.events_read += len(events)
        self.t_last = float(events.t[-1])
        for packet in self.runner.slicer.push(every_qth(events, self._q_front, offset)):
            self._packet(packet)
        self._receive()
        while self.max_backlog is not None and self._worker is not None and \
                self.t_last - self.refined_until > self.max_backlog:
            self._send_events()
            tic = time.perf_counter()
            self._receive(until="window")
            self._worker.blocked_seconds += time.perf_counter() - tic

    def close(self) -> SlamResult:
        """End of the stream: process the last packets and windows; the same result as ``run_slam``."""
        if self._result is not None:
            return self._result
        for packet in self.runner.slicer.flush():
            self._packet(packet)
        if self._feed.backend is None or self._t_prev is None:  # no events, or no packet: nothing to refine
            if self._worker is not None:
                self._worker.cancel()
            raise InputError("no events to process" if self._feed.backend is None else NO_MOTION_MEASURABLE)
        if self._worker is not None:
            self._send_events()
            self._worker.send(("finish",))
            done = self._receive(until="done")
            self._worker.stop()
            self.backend_seconds, self.backend_cpu_seconds = done["seconds"], done["step_cpu_seconds"]
            self._result = self._assemble(done["report"], done["spline"], done["map"], done["windows"], done)
            return self._result
        backend = self._feed.backend
        done = len(backend.windows)
        tic, cpu = time.perf_counter(), time.process_time()
        if backend.loop is not None:  # the end of the stream: a sliced verification in flight at once
            backend.loop.drain()
        backend.finish()
        self.backend_seconds += time.perf_counter() - tic
        self.backend_cpu_seconds += time.process_time() - cpu
        for report in backend.windows[done:]:
            self._notify(report)
        self._result = self._assemble(_backend_report(backend, self.backend_seconds), backend.spline,
                                      backend.map.raw, backend.windows, None)
        return self._result

    def degrade(self, frontend_keep: int = 1, ba_cap: int | None = None, ba_every: int = 1,
                ba_budget: float | None = None, input_thinning: int = 1) -> None:
        """Real-time degradation (pipelines/realtime.py): from now on the front-end processes 1 of
        ``frontend_keep`` packets and the BA uses at most ``ba_cap`` events per window (None: the config's cap;
        0: BA skipped, the window keeps the front-end's poses) on 1 of ``ba_every`` windows (the others are skipped
        like ba_cap 0: their strides keep the poses the previous window refined), and starts no BFGS iteration
        after ``ba_budget`` seconds (None: no budget). ``input_thinning`` q: the caller hands over 1 of q events, so
        a packet takes N / q of them (the same time span, at least the minimum span: the front-end's cost falls with
        the input; with N it would span q times longer and cost as much: VGA at 12.6 M ev/s kept 71 000-event
        packets at 1 of 16). ``degrade()`` restores the full computation. Values out of these ranges raise
        ValueError (they meant different things in one process and in the worker, which shares them as integers)."""
        counts = {"frontend_keep": frontend_keep, "ba_every": ba_every, "input_thinning": input_thinning}
        for name, value in counts.items():
            if int(value) != value or value < 1:
                raise ValueError(f"degrade: {name} must be an integer >= 1, got {value!r}")
        if ba_cap is not None and (int(ba_cap) != ba_cap or ba_cap < 0):
            raise ValueError(f"degrade: ba_cap must be None or an integer >= 0, got {ba_cap!r}")
        if ba_budget is not None and not ba_budget >= 0:
            raise ValueError(f"degrade: ba_budget must be None or >= 0 seconds, got {ba_budget!r}")
        ba_cap = None if ba_cap is None else int(ba_cap)
        self.frontend_keep = int(frontend_keep)
        self.runner.slicer.n = max(1, int(self._packet_events) // int(input_thinning))
        self._ba_cap, self._ba_every, self._ba_budget = ba_cap, int(ba_every), ba_budget
        if self._worker is not None:  # shared memory: acts at the worker's next window, not behind its queue
            self._worker.ba_cap.value = -1 if ba_cap is None else int(ba_cap)
            self._worker.ba_every.value = self._ba_every
            self._worker.ba_budget.value = -1.0 if ba_budget is None else float(ba_budget)
        elif self._feed.backend is not None:
            self._apply_degradation(self._feed.backend)

    def _apply_degradation(self, backend) -> None:
        backend.ba_cap, backend.ba_every, backend.ba_budget = self._ba_cap, self._ba_every, self._ba_budget

    def wait_ready(self) -> None:
        """With a worker process: wait until it has prepared its kernels (a live source starts after this)."""
        if self._worker is not None and not self._worker.ready:
            self._receive(until="ready")

    def abort(self) -> None:
        """Stop at once (Ctrl-C): end the back-end worker process, if any, without waiting for its results."""
        if self._worker is not None and self._worker.proc.is_alive():
            self._worker.proc.terminate()

    # ---- estimates so far ----------------------------------------------------------------------------------------
    @property
    def frontend_until(self) -> float | None:
        """Centre time of the last front-end packet (its integrated pose is known up to there)."""
        return self._t_prev

    @property
    def refined_until(self) -> float | None:
        """Windows are done (events settled into the map) up to this time; None before the first event."""
        backend = self._feed.backend
        if backend is None:
            return None
        return backend.window_start if backend.windows else backend.t_start

    def pose(self, t) -> np.ndarray:
        """R_world_from_camera (M, 3, 3) at times t: the refined spline where windows are done, the integrated
        front-end beyond (extrapolated at the last angular velocity past the last packet)."""
        backend = self._feed.backend
        if backend is None:
            return np.broadcast_to(np.eye(3), (np.size(t), 3, 3)).copy()
        return backend.pose_at(t)

    def latest(self) -> tuple[float, np.ndarray]:
        """(time of the last event pushed, the best estimate of R there)."""
        if self.t_last is None:
            raise RuntimeError("no events pushed yet")
        return self.t_last, self.pose(self.t_last)[0]

    def map(self) -> np.ndarray:
        """Copy of the panoramic map I_G of the events settled so far, (h, w) float32. With a worker process the
        worker sends a copy once it has handled everything pushed before (this call waits for it)."""
        backend = self._feed.backend
        if self._result is not None:
            return self._result.map.copy()
        if backend is not None and self._worker is not None:
            self._send_events()
            self._worker.send(("map",))
            snapshot = self._receive(until="map")
            if snapshot is not None:
                return snapshot
        elif backend is not None:
            return backend.map.raw.copy()
        w, h = self.config.backend.pano_size
        return np.zeros((h, w), np.float32)

    # ---- internals -----------------------------------------------------------------------------------------------
    def _packet(self, packet: Packet) -> None:
        self.packets_seen += 1
        if self.frontend_keep > 1 and (self.packets_seen - 1) % self.frontend_keep:
            self.packets_skipped += 1  # real-time thinning: no omega here, the next packet integrates across
            return
        row = self.runner.process(packet)
        omega = row.omega
        if self._t_prev is not None:
            self._r_src = self._r_src @ so3.exp(0.5 * (self._w_prev + omega) * (packet.t_ref - self._t_prev))
        self._t_prev, self._w_prev = packet.t_ref, omega
        backend = self._feed.backend
        moving = [not row.motion.still]
        backend.push_source_poses([packet.t_ref], self._r_src[None], moving)
        if self._worker is not None:
            self._send_events()  # every event pushed so far goes before the pose, as in the sequential run
            self._worker.send(("pose", packet.t_ref, self._r_src, moving))
            return
        while backend.ready():
            tic, cpu = time.perf_counter(), time.process_time()
            report = backend.step()
            self.backend_seconds += time.perf_counter() - tic
            self.backend_cpu_seconds += time.process_time() - cpu
            self._notify(report)

    def _send_events(self) -> None:
        """Hand the chunks pushed since the last pose to the worker as one message (a live source or the real-time
        replay pushes many small chunks; each message costs a pickle, a pipe write and a wake-up of the worker)."""
        if self._to_send:
            chunks, self._to_send = self._to_send, []
            self._worker.send(("events", Events.concatenate(chunks)))

    def _receive(self, until: str | None = None):
        """Apply the worker's window messages to the shadow back-end (and call on_window); with ``until`` ("done",
        "map") wait for that message and return its content."""
        if self._worker is None:
            return None
        for kind, *args in self._worker.messages(until):
            if kind == "window":
                report, first, tail, anchor, window_start, shape = args
                shadow = self._feed.backend
                if shadow.spline is None:
                    shadow.spline = SO3Spline(*shape, tail)
                else:
                    shadow.spline.control_R = np.concatenate([shadow.spline.control_R[:first], tail])
                shadow._anchor, shadow.window_start = anchor, window_start
                shadow._drop_source_before_anchor()
                shadow.windows.append(report)
                self._notify(report)
            elif kind == until:
                return args[0]
        return None

    def _notify(self, report) -> None:
        if self.on_window is not None:
            self.on_window(report)

    def _assemble(self, backend_report: dict, spline, global_map, windows, worker) -> SlamResult:
        config, runner = self.config, self.runner
        frontend = runner.result()
        n = max(self.events_read, 1)
        report = {
            "status": frontend.status,
            "method": "cmax-slam",
            "events_processed": int(self.events_read),
            "wall_seconds": time.perf_counter() - self._wall0,
            "compile_seconds": self.compile_seconds,
            "startup": self.startup,
            "frontend": frontend.summary(),
            "backend": backend_report,
            # per event of the input stream, steady state (compilation apart)
            "us_per_event": {"frontend": runner.seconds * 1e6 / n, "backend": self.backend_seconds * 1e6 / n},
            "parameters": config_to_dict(config),
            "derived_parameters": self.derived,
        }
        loops = worker["loops"] if worker is not None else \
            (self._feed.backend.loop.loops if self._feed.backend.loop is not None else None)
        if loops is not None:
            report["loops"] = loops
        if worker is not None:
            report["backend_process"] = {"compile_seconds": worker["compile_seconds"],
                                         "cpu_seconds": worker["cpu_seconds"],
                                         "push_blocked_seconds": self._worker.blocked_seconds,
                                         "peak_rss_mb": worker["peak_rss_mb"]}
        trajectory = worker["trajectory"] if worker is not None else \
            self._feed.backend.trajectory(config.output.trajectory_rate)
        return SlamResult(spline, trajectory, global_map, report, frontend, windows)


class _BackendProcess:
    """The back-end in a spawned worker process (a forked one would hang after ti.init), connected by a bounded
    queue of inputs (``send`` blocks while it is full: back-pressure, nothing dropped) and a queue of results."""

    def __init__(self, camera: Camera, config: SlamConfig, queue_size: int, loop_slice_seconds: float | None = None,
                 threads: int | None = None):
        import multiprocessing as mp

        from ti_cmax.kernels import runtime

        exit_if_spawn_bootstrapping()  # in a worker re-running an unguarded script: one line, a known exit
        ctx = mp.get_context("spawn")
        self.inbox, self.outbox = ctx.Queue(max(1, queue_size)), ctx.Queue()
        self.inbox.cancel_join_thread()  # never hang at exit on a worker that stopped reading (it failed)
        self.ba_cap = ctx.Value("q", -1, lock=False)  # the back-end's ba_cap (-1: None), set by OnlineSlam.degrade
        self.ba_every = ctx.Value("q", 1, lock=False)  # and its ba_every
        self.ba_budget = ctx.Value("d", -1.0, lock=False)  # and its ba_budget (-1: None)
        self.proc = ctx.Process(target=_backend_worker, daemon=True,
                                args=(camera, config, threads or runtime.num_threads(), self.inbox, self.outbox,
                                      (self.ba_cap, self.ba_every, self.ba_budget), loop_slice_seconds))
        # Ctrl-C is this process's to handle (the CLI: one line, exit 130; OnlineSlam's caller stops the worker), but a
        # terminal sends it to the whole process group. Blocked while the worker is spawned, SIGINT stays blocked in
        # it from its first instruction (the mask survives fork and exec): neither its start-up imports nor its loop
        # print a traceback; a Ctrl-C meanwhile reaches this process when unblocked (as multiprocessing's own
        # resource_tracker does)
        import signal

        mask = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT}) if hasattr(signal, "pthread_sigmask") else None
        try:
            self.proc.start()
        finally:
            if mask is not None:
                signal.pthread_sigmask(signal.SIG_SETMASK, mask)
        self.blocked_seconds = 0.0
        self.ready = False  # the worker has prepared its kernels

    def send(self, message) -> None:
        """Put a message on the inbox, waiting while it is full (1 s timeouts, to notice a worker that ended)."""
        import queue

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
        self.blocked_seconds += time.perf_counter() - tic

    def _ended(self, what: str) -> str:
        """Why the worker is gone, in one line."""
        if self.proc.exitcode == UNGUARDED_MAIN_EXIT:
            return f"the back-end worker could not start: {UNGUARDED_MAIN}, or pass backend_process=False"
        return f"the back-end process ended{what} (exit {self.proc.exitcode}: killed or out of memory?)"

    def messages(self, until: str | None):
        """Messages ready now; with ``until`` (a message kind: "done", "map") block (1 s timeouts, to notice a dead
        worker) until that message."""
        import queue

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
        self.proc.terminate()
        self.proc.join(timeout=10)


def _next_message(inbox, poll: float = 1.0):
    """The worker's next message; it exits when its parent process has died meanwhile (killed, or out of memory):
    otherwise it would sleep forever, holding the terminal's pipes open (``slam | tee log`` never ended)."""
    import multiprocessing
    import queue

    while True:
        try:
            return inbox.get(timeout=poll)
        except queue.Empty:
            parent = multiprocessing.parent_process()
            if parent is not None and not parent.is_alive():
                os._exit(1)


def _backend_worker(camera: Camera, config: SlamConfig, threads: int, inbox, outbox, degradation,
                    loop_slice_seconds: float | None = None) -> None:
    """Worker process: the sequential back-end loop on messages ("events", chunk), ("pose", t, R, moving), ("map",)
    (send a copy of the map) and ("finish",); ``degradation``: the back-end's ba_cap, ba_every and ba_budget in
    shared memory (-1: None; set by OnlineSlam.degrade), read before each step. With ``loop_slice_seconds`` a loop
    verification runs in slices (LoopCloser.slice_seconds): also one slice at a time while no message waits (idle
    time)."""
    try:
        from ti_cmax import progress
        from ti_cmax.kernels import runtime

        progress.set_quiet(True)  # no bars here, nor Taichi's start-up line (the main process shows its own)
        runtime.set_num_threads(threads)
        cpu0 = time.process_time()
        compile_s = _compile_backend(config)
        outbox.put(("ready", compile_s))
        feed = _BackendFeed(camera, config, lambda t0: np.eye(3), loop_slice_seconds)
        seconds = step_cpu = 0.0
        loops_applied = 0  # an applied loop moves control poses before the window: send them all then
        # per-stage costs of the worker loop: receive (waiting for input and unpickling it: wall; unpickling: CPU),
        # events (bearings and the window buffer), send (the window messages); the back-end's own stages beside
        clock = StageClock()
        last_done, waited = time.perf_counter(), 0.0  # busy_seconds of a window: wall since the last one - waited
        while True:
            loop = feed.backend.loop if feed.backend is not None else None
            while loop is not None and loop.pending() and inbox.empty():  # idle: the verification in flight
                with clock("loop_idle"):
                    loop.idle_slice()
            tic = time.perf_counter()
            with clock("receive"):
                kind, *args = _next_message(inbox)
            waited += time.perf_counter() - tic
            if kind == "events":
                with clock("events"):
                    feed.push(args[0])
                continue
            backend = feed.backend
            if kind == "map":  # OnlineSlam.map(): a copy of the map of the events settled so far
                outbox.put(("map", backend.map.raw.copy() if backend is not None else None))
                continue
            ba_cap, ba_every, ba_budget = (v.value for v in degradation)  # OnlineSlam.degrade
            backend.ba_cap = None if ba_cap < 0 else int(ba_cap)
            backend.ba_every = int(ba_every)
            backend.ba_budget = None if ba_budget < 0 else float(ba_budget)
            tic, cpu = time.perf_counter(), time.process_time()
            if kind == "pose":
                backend.push_source_poses([args[0]], args[1][None], args[2])
                new = len(backend.windows)
                while backend.ready():
                    backend.step()
            else:
                new = len(backend.windows)
                if backend.loop is not None:  # the end of the stream: the verification in flight at once
                    backend.loop.drain()
                backend.finish()
            seconds += time.perf_counter() - tic
            step_cpu += time.process_time() - cpu
            spline = backend.spline
            applied = backend.loop.corrections if backend.loop is not None else 0
            for report in backend.windows[new:]:
                now = time.perf_counter()
                report.busy_seconds, last_done, waited = max(0.0, now - last_done - waited), now, 0.0
                # control poses before the window's first free one (minus one) did not change, unless a loop was
                # closed
                # ... and those a fit changed (after a pause: its windows are fitted with a later one)
                fitted = backend.fitted_from if backend.fitted_from is not None else len(spline.control_R)
                first = 0 if applied > loops_applied else \
                    max(0, min(int(np.floor((report.t_start - spline.t0) / spline.dt)) - 1, fitted))
                loops_applied, backend.fitted_from = applied, None
                with clock("send"):
                    outbox.put(("window", report, first, spline.control_R[first:].copy(), backend._anchor,
                                backend.window_start, (spline.degree, spline.t0, spline.dt)))
            if kind == "finish":
                worker_report = _backend_report(backend, seconds)
                worker_report["worker_stages"] = clock.summary()
                outbox.put(("done", {
                    "report": worker_report, "spline": spline, "map": backend.map.raw,
                    "windows": backend.windows, "trajectory": backend.trajectory(config.output.trajectory_rate),
                    "seconds": seconds, "step_cpu_seconds": step_cpu, "compile_seconds": compile_s,
                    "cpu_seconds": time.process_time() - cpu0, "peak_rss_mb": peak_rss_mb(),
                    "loops": backend.loop.loops if backend.loop is not None else None}))
                return
    except BaseException as exc:  # noqa: BLE001 - reported to the parent, which raises it
        outbox.put(("error", f"{type(exc).__name__}: {exc}"))


# sensors up to this many pixels get a back-end worker by default (default_backend_process): VGA-class and below
WORKER_MAX_SENSOR_PIXELS = 500_000


def default_backend_process(camera: Camera) -> bool:
    """Whether ``ti-cmax slam`` (and the demo) run the back-end in a worker process when neither --parallel nor
    --sequential is given. Rule: yes when this process may run on 2 or more cores (its CPU affinity) and the sensor
    has at most ``WORKER_MAX_SENSOR_PIXELS`` (0.5 M) pixels. The front-end then runs beside the back-end (paper
    Fig. 3), each process on half the cores, and a run costs about the slower of the two instead of their sum:
    measured on 2 cores, whole process, DAVIS240C 3 s (2.9 M events, linear) 4.4 s median against 5.2 s in one
    process (4 interleaved pairs), DVXplorer 640x480 1.5 s -20 %. On an HD sensor (1280x720) the back-end's kernels
    use both cores well (0.45 -> 0.28 us per event from 1 to 2 threads), so the split gained nothing (32.7 s against
    31.7 s, 51 M events) and held ~240 MB more (two processes: 1.47 GB against 1.23 GB). On one core a worker would
    only add its start-up; where the platform has no working semaphores (multiprocessing's queues need them, e.g.
    some sandboxes) it stays in one process too. The Python API (``run_slam``, ``OnlineSlam``) stays in one process
    unless asked: a worker process needs the caller's main module to be importable (multiprocessing's spawn)."""
    from ti_cmax.kernels import runtime

    if runtime.available_cores() < 2 or camera.width * camera.height > WORKER_MAX_SENSOR_PIXELS:
        return False
    try:
        import multiprocessing.synchronize  # noqa: F401 - raises ImportError without a working sem_open
    except ImportError:
        return False
    return True


def run_slam(events_or_chunks, camera: Camera, config: SlamConfig = SlamConfig(), *,
             progress_total: float | None = None, backend_process: bool = False) -> SlamResult:
    """CMax-SLAM on an ``Events`` object, an iterable of time-ordered chunks, or a dataset (``iter_events``).

    The trajectory starts at the identity at the first event (the world frame is the first camera frame).
    ``backend_process``: run the back-end in a worker process at the same time as the front-end (OnlineSlam).
    """
    online = OnlineSlam(camera, config, backend_process=backend_process)
    bar = progress(total=progress_total, desc="slam", unit="s")
    try:
        shown = None
        for chunk in as_chunks(events_or_chunks):
            online.push(chunk)
            if online.frontend_until is not None:
                bar.update(online.frontend_until - (shown if shown is not None else online.frontend_until))
                shown = online.frontend_until
        return online.close()
    finally:
        bar.close()


def _at_frontend_rate(trajectory: Trajectory, dt: float) -> Trajectory:
    if len(trajectory) < 3 or np.median(np.diff(trajectory.t)) >= 0.999 * dt:
        return trajectory
    times = np.arange(trajectory.t_start, trajectory.t_end, dt)
    if trajectory.t_end - times[-1] > 1e-9:
        times = np.append(times, trajectory.t_end)
    return trajectory.resampled(times)


def refine(events_or_chunks, camera: Camera, trajectory: Trajectory, config: SlamConfig = SlamConfig(), *,
           progress_total: float | None = None) -> SlamResult:
    """Offline BA: refine a given trajectory over the whole stream with the sliding-window machinery.

    The result stays in the given trajectory's world frame (it starts from the given pose at the first event).
    Events outside the given trajectory's time range are ignored. Trajectories sampled faster than the front-end
    (IMU at 1 kHz, RTPT per packet) are resampled at 1/dt_ang_vel first: the back-end initializes from poses at
    the front-end's rate (with 1 kHz sources the cubic fit was measured to end windows worse: 0.31 vs 0.11 deg).
    """
    wall0 = time.perf_counter()
    derived = derived_summary(config, camera)
    config = resolve_config(config, camera)
    trajectory = _at_frontend_rate(trajectory, config.frontend.dt_ang_vel)
    compile_s = _compile_backend(config)
    feed = _BackendFeed(camera, config, lambda t0: trajectory.at(t0)[0])
    inside = (ev.slice_time(trajectory.t_start, np.nextafter(trajectory.t_end, np.inf))
              for ev in as_chunks(events_or_chunks))
    tic = time.perf_counter()
    bar = progress(total=progress_total, desc="refine", unit="s")
    last = None
    try:
        for chunk in feed(inside):
            if last is None:
                feed.backend.push_source_poses(trajectory.t, trajectory.R)
            while feed.backend.ready():
                feed.backend.step()
            if last is not None:
                bar.update(float(chunk.t[-1]) - last)
            last = float(chunk.t[-1])
        if feed.backend is None:
            raise InputError("no events within the trajectory's time range "
                             f"[{trajectory.t_start:.6f}, {trajectory.t_end:.6f}] s")
        feed.backend.finish()
    finally:
        bar.close()
    backend = feed.backend
    backend_seconds = time.perf_counter() - tic
    events_read = feed.events_read
    report = {
        "status": "ok",
        "method": "cmax-ba",
        "events_processed": int(events_read),
        "wall_seconds": time.perf_counter() - wall0,
        "compile_seconds": compile_s,
        "backend": _backend_report(backend, backend_seconds),
        "us_per_event": {"backend": backend_seconds * 1e6 / max(events_read, 1)},
        "parameters": config_to_dict(config),
        "derived_parameters": derived,
        **({"loops": backend.loop.loops} if backend.loop is not None else {}),
    }
    return SlamResult(backend.spline, backend.trajectory(config.output.trajectory_rate), backend.map.raw,
                      report, None, backend.windows)
