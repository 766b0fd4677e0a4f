"""CMax-SLAM (paper Fig. 3): front-end and back-end run in time order over one stream of events.

events -> packets around equispaced times -> omega per packet (front-end) -> integrated source poses ->
sliding-window BA on the panoramic IWE (back-end) -> continuous trajectory + panoramic map.

``OnlineSlam`` is the streaming form (push chunks from a live source, ask for poses at any time) and ``run_slam``
a thin wrapper over it: each event chunk is read once, feeds the front-end's slicer and the back-end's window
buffer, and every window is refined as soon as the front-end has covered it, so memory is bounded by the chunk
size plus one window. The back-end runs in this process or in a worker process behind one interface
(pipelines/online_backend.py, pipelines/worker.py). ``refine`` is the offline BA (Sec. IV-C2): the same back-end
initialized from any given trajectory (another method's output, IMU dead reckoning) instead of the front-end.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from ti_cmax import so3, timeline
from ti_cmax.camera import Camera
from ti_cmax.config import SlamConfig, config_to_dict
from ti_cmax.errors import InputError
from ti_cmax.events import Events
from ti_cmax.progress import StageBars, stage
from ti_cmax.spline import SO3Spline
from ti_cmax.trajectory import Trajectory

from .backend_policies import FULL_BUDGET, WindowBudget
from .frontend import NO_MOTION_MEASURABLE, FrontendResult, FrontendRunner, Packet, as_chunks, every_qth
from .hot_pixels import HotPixelFilter
from .online_backend import BackendOutcome, BackendRunner, OnlineBackend
from .sensor_defaults import derived_summary, resolve_config
from .worker import WORKER_MAX_SENSOR_PIXELS, WorkerBackend, default_backend_process  # noqa: F401 - re-exported


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


class OnlineSlam:
    """CMax-SLAM on a live stream: push time-ordered event chunks as they arrive, ask for poses at any time.

    The computation of :func:`run_slam` (a thin wrapper over this class): each chunk feeds the back-end's window
    buffer and the front-end's packet slicer; each packet's omega is integrated into the source poses, and every
    window is refined as soon as the front-end has covered it. Chunks may have any size (a camera driver's
    packets, a ROS message); the results do not depend on it. ``on_window(report)`` is called after every window
    the back-end completes (a :class:`~ti_cmax.pipelines.backend.WindowReport`); ``close()`` ends the stream and
    returns the :class:`SlamResult` that ``run_slam`` returns. The trajectory starts at the identity at the first
    event (the world frame is the first camera frame). Events pass the hot-pixel filter first
    (pipelines/hot_pixels.py), which holds the start of the stream back until its first test (at most
    ``hot_pixel_hold_time`` of sensor time; 0.05-0.2 s on a DAVIS240C): until then ``pose`` is the world frame.

    The back-end is an ``online_backend.OnlineBackend``: in this process, or with ``backend_process=True`` in a
    worker process at the same time as the front-end (paper Fig. 3; pipelines/worker.py), with the same results.
    With a worker ``pose`` uses the refined spline the worker last sent, ``queue_size`` bounds the messages in
    flight and ``max_backlog`` (sensor seconds) makes ``push`` wait while it runs that far ahead of the worker's
    last window; ``worker_threads``: the worker's Taichi threads. ``loop_slice_seconds``: loop verifications in
    slices of at most this many wall seconds per window (the real-time replay).

    ``degrade`` (used by the real-time replay, pipelines/realtime.py) skips front-end packets and sets the budget
    of the back-end's windows from then on; by default nothing is degraded.
    """

    def __init__(self, camera: Camera, config: SlamConfig = SlamConfig(), *, on_window=None, on_packet=None,
                 backend_process: bool = False, queue_size: int = 16, max_backlog: float | None = None,
                 loop_slice_seconds: float | None = None, worker_threads: int | None = None):
        self._wall0 = time.perf_counter()
        self.derived = derived_summary(config, camera)
        self.config = config = resolve_config(config, camera)
        self.on_window = on_window
        self.on_packet = on_packet  # observer of each front-end packet: on_packet(packet, omega) (ti_cmax.viewer)
        self.backend: OnlineBackend = \
            WorkerBackend(camera, config, queue_size, max_backlog, loop_slice_seconds, worker_threads) \
            if backend_process else BackendRunner(camera, config, loop_slice_seconds=loop_slice_seconds)
        self.runner = FrontendRunner(camera, config.frontend)
        # hot pixels' events are dropped before anything else sees them (pipelines/hot_pixels.py); the start of the
        # stream is held back until the first block of events is tested
        self.hot_pixels = HotPixelFilter(camera.width, camera.height, config.frontend)
        self._packet_events = self.runner.slicer.n  # N of the resolved config (degrade's input thinning divides it)
        cpu0 = time.process_time()
        self.compile_seconds = self.runner.compile() + self.backend.compile()
        # what the process paid before the first event: imports, ti.init, kernel preparation (CPU seconds, which
        # a loaded machine does not inflate, unlike wall time); a worker's own start-up runs meanwhile
        self.startup = {"compile_seconds": self.compile_seconds,
                        "compile_cpu_seconds": time.process_time() - cpu0,
                        "process_cpu_seconds": time.process_time()}
        timeline.mark("ready")
        self._q_front = int(config.frontend.frontend_event_sample_rate)
        self._r_src = np.eye(3)
        self._t_prev: float | None = None
        self._first: list | None = None  # the first packet's source samples while it is the only one (_packet)
        self._w_prev: np.ndarray | None = None
        self.t_last: float | None = None  # time of the last event pushed
        self._t_used: float | None = None  # time of the last event passed on to the front-end and the back-end
        self.events_read = 0  # events pushed
        self._events_used = 0  # of them, passed on (the hot pixels' dropped, a held-back start not yet)
        # real-time degradation (``degrade``): the front-end processes 1 of frontend_keep packets (the others are
        # skipped: integration goes on from the last processed one); the back-end's windows get ``budget``
        self.frontend_keep = 1
        self.budget = FULL_BUDGET
        self.packets_seen = self.packets_skipped = 0
        # CPU seconds of this process in push() beside the front-end's estimation: "ingest" (checks, hot-pixel filter,
        # slicing, pose integration), "handover" (the back-end's calls less its windows: to a worker, the ring writes
        # and messages; in this process, bearings and the window buffer), "callbacks" (on_window, on_packet) and
        # "close" (close() less the estimation and windows: the last packets' slicing, a worker's outcome)
        self.cpu_seconds = {"ingest": 0.0, "handover": 0.0, "callbacks": 0.0, "close": 0.0}
        self._result: SlamResult | None = None

    @property
    def backend_seconds(self) -> float:
        """Steady-state wall seconds in the back-end's windows, callbacks excluded."""
        return self.backend.seconds

    @property
    def backend_cpu_seconds(self) -> float:
        """CPU seconds of this process in the back-end's windows (0 with a worker)."""
        return self.backend.cpu_seconds

    # ---- input ---------------------------------------------------------------------------------------------------
    def push(self, events: Events) -> None:
        """Process a time-ordered chunk (continuing the previous ones): every packet and window it completes."""
        kept = self.screen(events)
        if len(events):
            self._take(kept)

    def screen(self, events: Events) -> list[Events]:
        """The first half of ``push``: check a time-ordered chunk (one clear InputError) and pass it through the
        hot-pixel filter; returns what ``push_screened`` takes next (nothing while the start is held back). A replay
        screens each chunk it reads at once and hands the screened events over when they are due
        (pipelines/realtime.py): the filter then counts whole read chunks, while its per-pixel counts are in the
        cache, instead of every hand-over's few events after the front-end's work has evicted them."""
        if self._result is not None:
            raise RuntimeError("push() after close()")
        if not isinstance(events, Events):
            raise InputError(f"expected Events chunks, got {type(events).__name__}")
        if len(events) == 0:
            return []
        cpu0 = time.process_time()
        self.runner.check(events)  # times, pixels and pauses (one clear InputError)
        self.events_read += len(events)
        self.t_last = float(events.t[-1])
        kept = self.hot_pixels.push(events)
        self.cpu_seconds["ingest"] += time.process_time() - cpu0
        return kept

    def push_screened(self, events: Events) -> None:
        """The second half of ``push``: screened events (``screen``, in stream order) to the back-end's window buffer
        and the front-end's slicer; every packet and window they complete."""
        if self._result is not None:
            raise RuntimeError("push() after close()")
        if len(events):
            self._take([events])

    def _take(self, parts: list[Events]) -> None:
        cpu = self.cpu_seconds
        cpu0, fe0 = time.process_time(), self.runner.cpu_seconds + self._window_cpu()
        other0 = cpu["handover"] + cpu["callbacks"]
        for part in parts:
            self._use(part)
        self._notify(self._backend_call(lambda: self.backend.poll(self._t_used)))
        cpu["ingest"] += time.process_time() - cpu0 - (self.runner.cpu_seconds + self._window_cpu() - fe0) \
            - (cpu["handover"] + cpu["callbacks"] - other0)

    def _window_cpu(self) -> float:
        """CPU seconds of this process in the back-end's windows (a worker reports its own at the end: not ours)."""
        return 0.0 if isinstance(self.backend, WorkerBackend) else self.backend.cpu_seconds

    def _backend_call(self, call):
        """``call()``, its CPU time counted as "handover" (the windows it runs in this process left out)."""
        tic, windows = time.process_time(), self._window_cpu()
        out = call()
        self.cpu_seconds["handover"] += time.process_time() - tic - (self._window_cpu() - windows)
        return out


    def _use(self, events: Events) -> None:
        """Events that passed the hot-pixel filter: to the back-end's window buffer and the front-end's slicer."""
        offset = self._events_used
        self._backend_call(lambda: self.backend.push_events(events))
        self._events_used += len(events)
        self._t_used = float(events.t[-1])
        for packet in self.runner.slicer.push(every_qth(events, self._q_front, offset)):
            self._packet(packet)

    def close(self) -> SlamResult:
        """End of the stream: process the last packets and windows; the same result as ``run_slam``."""
        if self._result is not None:
            return self._result
        cpu0, work0 = time.process_time(), self.runner.cpu_seconds + self._window_cpu()
        try:
            return self._close()
        finally:  # the front-end's estimation and the windows in this process are theirs
            work = self.runner.cpu_seconds + self._window_cpu() - work0
            self.cpu_seconds["close"] += time.process_time() - cpu0 - work

    def _close(self) -> SlamResult:
        for kept in self.hot_pixels.flush():
            self._use(kept)
        for packet in self.runner.slicer.flush():
            self._packet(packet)
        if self._first is not None and len(self._first) == 2:
            # a stream of one packet: its omega holds from its first event (alone, the source would stand still)
            first, only = self._first
            self._push_source([first, only] if first[0] < only[0] else [only])
            self._first[1:] = []
        if not self.backend.started or self._t_prev is None:  # no events, or no packet: nothing to refine
            self.backend.abort()
            if not self.backend.started:
                raise InputError(self.hot_pixels.all_dropped() or "no events to process")
            raise InputError(NO_MOTION_MEASURABLE)
        timeline.mark("frontend_done")
        reports, outcome = self.backend.finish(self.budget)
        timeline.mark("closed")
        self._notify(reports)
        self._result = self._assemble(outcome)
        return self._result

    def degrade(self, frontend_keep: int = 1, ba_cap: int | None = None, ba_every: int = 1,
                ba_budget: float | None = None, input_thinning: int = 1, loop_idle_only: bool = False) -> None:
        """Real-time degradation (pipelines/realtime.py): from now on the front-end processes 1 of
        ``frontend_keep`` packets and the back-end's windows get the budget (``WindowBudget``: at most ``ba_cap``
        BA events, 0 skipping the BA; the BA on 1 of ``ba_every`` windows; no BFGS iteration started after
        ``ba_budget`` seconds). ``input_thinning`` q: the caller hands over 1 of q events, so a packet takes N / q of
        them (the same time span: the front-end's cost falls with the input). ``loop_idle_only``: the loop closer's
        work in flight waits for the back-end's idle time (no slice before each window). ``degrade()`` restores the full
        computation. Values out of these ranges raise ValueError."""
        for name, value in {"frontend_keep": frontend_keep, "input_thinning": input_thinning}.items():
            if int(value) != value or value < 1:
                raise ValueError(f"degrade: {name} must be an integer >= 1, got {value!r}")
        try:
            budget = WindowBudget(ba_cap, ba_every, ba_budget, loop_idle_only)
        except ValueError as exc:
            raise ValueError(f"degrade: {exc}") from None
        self.frontend_keep = int(frontend_keep)
        self.runner.slicer.n = max(1, int(self._packet_events) // int(input_thinning))
        self.budget = budget

    def wait_ready(self) -> None:
        """With a worker process: wait until it has prepared its kernels (a live source starts after this)."""
        self.backend.wait_ready()

    def prepare(self, rate: float) -> None:
        """Before the first events: the back-end's memory for a stream of ``rate`` events/s, written once now
        (``BackendRunner.prepare``; a real-time replay calls it before its clock starts)."""
        self.backend.prepare(rate)

    def abort(self) -> None:
        """Stop at once (Ctrl-C): end the back-end worker process, if any, without waiting for its results."""
        self.backend.abort()

    # ---- estimates so far ----------------------------------------------------------------------------------------
    @property
    def frontend_until(self) -> float | None:
        """Centre time of the last front-end packet (its integrated pose is known up to there)."""
        return self._t_prev

    @property
    def refined_until(self) -> float | None:
        """Windows are done (events settled into the map) up to this time; None before the first event."""
        return self.backend.refined_until()

    def pose(self, t) -> np.ndarray:
        """R_world_from_camera (M, 3, 3) at times t: the refined spline where windows are done, the integrated
        front-end beyond (extrapolated at the last angular velocity past the last packet)."""
        return self.backend.pose(t)

    def latest(self) -> tuple[float, np.ndarray]:
        """(time of the last event pushed, the best estimate of R there)."""
        if self.t_last is None:
            raise RuntimeError("no events pushed yet")
        return self.t_last, self.pose(self.t_last)[0]

    def map(self) -> np.ndarray:
        """Copy of the panoramic map I_G of the events settled so far, (h, w) float32. With a worker process the
        worker sends a copy once it has handled everything pushed before (this call waits for it)."""
        if self._result is not None:
            return self._result.map.copy()
        snapshot = self.backend.map()
        if snapshot is not None:
            return snapshot
        w, h = self.config.backend.pano_size
        return np.zeros((h, w), np.float32)

    # ---- internals -----------------------------------------------------------------------------------------------
    def _packet(self, packet: Packet) -> None:
        """Integrate one packet's omega into the source pose and hand it to the back-end (paper Fig. 3)."""
        self.packets_seen += 1
        if self.frontend_keep > 1 and (self.packets_seen - 1) % self.frontend_keep:
            self.packets_skipped += 1  # real-time thinning: no omega here, the next packet integrates across
            return
        row = self.runner.process(packet)
        omega = row.omega
        if self._t_prev is not None:
            self._r_src = self._r_src @ so3.exp(0.5 * (self._w_prev + omega) * (packet.t_ref - self._t_prev))
        self._t_prev, self._w_prev = packet.t_ref, omega
        if self.on_packet is not None:
            tic = time.process_time()
            self.on_packet(packet, omega)
            self.cpu_seconds["callbacks"] += time.process_time() - tic
        sample = (packet.t_ref, self._r_src, not row.motion.still)  # moving: windows over it get a BA
        if self._first is None:  # held until a second packet (sent as before) or the close (a one-packet stream)
            t_first = float(packet.events.t[0]) if len(packet.events) else packet.t_ref
            self._first = [(t_first, so3.exp(-omega * (packet.t_ref - t_first)), sample[2]), sample]
            return
        self._push_source([*self._first[1:], sample])
        self._first[1:] = []

    def _push_source(self, samples) -> None:
        """Source poses (t, R, moving) to the back-end; then every window that became ready."""
        for t, rotation, moving in samples:
            self._notify(self.backend.advance(t, rotation, moving, lambda: self.budget))

    def _notify(self, reports) -> None:
        """Hand each window's report to on_window as the back-end yields it (the callback may degrade the next
        window); the back-end's own time counts as "handover" CPU, the callback's as the caller's."""
        reports = iter(reports)
        while True:
            report = self._backend_call(lambda: next(reports, None))
            if report is None:
                return
            if self.on_window is not None:
                tic = time.process_time()
                self.on_window(report)
                self.cpu_seconds["callbacks"] += time.process_time() - tic

    def _assemble(self, outcome: BackendOutcome) -> SlamResult:
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
            "backend": outcome.report,
            # per event of the input stream, steady state (compilation apart)
            "us_per_event": {"frontend": runner.seconds * 1e6 / n, "backend": self.backend_seconds * 1e6 / n},
            "parameters": config_to_dict(config),
            "derived_parameters": self.derived,
            "hot_pixels": self.hot_pixels.summary(),
        }
        if outcome.loops is not None:
            report["loops"] = outcome.loops
        if outcome.process is not None:
            report["backend_process"] = outcome.process
        return SlamResult(outcome.spline, outcome.trajectory, outcome.map, report, frontend, outcome.windows)


def run_slam(events_or_chunks, camera: Camera, config: SlamConfig = SlamConfig(), *,
             progress_total: float | None = None, backend_process: bool = False, observer=None,
             on_start=None) -> SlamResult:
    """CMax-SLAM on an ``Events`` object, an iterable of time-ordered chunks, or a dataset (``iter_events``).

    The trajectory starts at the identity at the first event (the world frame is the first camera frame).
    ``backend_process``: run the back-end in a worker process at the same time as the front-end (OnlineSlam).
    ``observer``: OnlineSlam's ``on_packet`` and ``on_window``, and ``attach(online)`` (ti_cmax.viewer.RerunViewer).
    ``on_start()``: called once the kernels are prepared and the worker started, before the first event (the command
    line starts preparing its outputs there).
    """
    with stage("start-up and compile"):
        online = OnlineSlam(camera, config, backend_process=backend_process,
                            on_packet=getattr(observer, "on_packet", None),
                            on_window=getattr(observer, "on_window", None))
        if observer is not None:
            observer.attach(online)
    if on_start is not None:
        on_start()
    with StageBars(progress_total, ("reading", "front-end", "back-end")) as bars:
        for chunk in as_chunks(events_or_chunks):
            if len(chunk):
                bars.start(chunk.t[0])
            online.push(chunk)
            for name, t in (("reading", online.t_last), ("front-end", online.frontend_until),
                            ("back-end", online.refined_until)):
                bars.at(name, t)
        result = online.close()
        bars.done()
        return result


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
    the front-end's rate (the cubic fit to much denser sources ends windows worse).
    """
    wall0 = time.perf_counter()
    derived = derived_summary(config, camera)
    config = resolve_config(config, camera)
    trajectory = _at_frontend_rate(trajectory, config.frontend.dt_ang_vel)
    feed = BackendRunner(camera, config, lambda t0: trajectory.at(t0)[0])
    with stage("start-up and compile"):
        compile_s = feed.compile()
    inside = (ev.slice_time(trajectory.t_start, np.nextafter(trajectory.t_end, np.inf))
              for ev in as_chunks(events_or_chunks))
    hot_pixels = HotPixelFilter(camera.width, camera.height, config.frontend)
    tic = time.perf_counter()
    with StageBars(progress_total, ("reading", "back-end")) as bars:
        for chunk in feed.feed(hot_pixels.filter(inside)):
            if bars.t0 is None:  # the first chunk: the back-end exists from here
                feed.backend.push_source_poses(trajectory.t, trajectory.R)
                bars.start(chunk.t[0])
            bars.at("reading", float(chunk.t[-1]))
            while feed.backend.ready():
                feed.backend.step()
            bars.at("back-end", feed.backend.window_start)
        if feed.backend is None:
            raise InputError(hot_pixels.all_dropped() or "no events within the trajectory's time range "
                             f"[{trajectory.t_start:.6f}, {trajectory.t_end:.6f}] s")
        feed.backend.finish()
        bars.done()
    backend_seconds = time.perf_counter() - tic
    events_read = hot_pixels.events_seen
    feed.seconds = backend_seconds
    outcome = feed.outcome()
    report = {
        "status": "ok",
        "method": "cmax-ba",
        "events_processed": int(events_read),
        "wall_seconds": time.perf_counter() - wall0,
        "compile_seconds": compile_s,
        "backend": outcome.report,
        "us_per_event": {"backend": backend_seconds * 1e6 / max(events_read, 1)},
        "parameters": config_to_dict(config),
        "derived_parameters": derived,
        "hot_pixels": hot_pixels.summary(),
        **({"loops": outcome.loops} if outcome.loops is not None else {}),
    }
    return SlamResult(outcome.spline, outcome.trajectory, outcome.map, report, None, outcome.windows)
