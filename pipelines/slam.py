"""CMax-SLAM (paper Fig. 3): front-end and back-end run in time order over one stream of events.

events -> packets around equispaced times -> omega per packet (front-end) -> integrated source poses ->
sliding-window BA on the panoramic IWE (back-end) -> continuous trajectory + panoramic map.

``run_slam`` is online: each event chunk is read once, feeds the front-end's slicer and the back-end's
window buffer, and every window is refined as soon as the front-end has covered it, so memory is bounded by
the chunk size plus one window. ``refine`` is the offline BA (Sec. IV-C2): the same back-end initialized from
any given trajectory (another method's output, IMU dead reckoning) instead of the front-end.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Iterable, Iterator

import numpy as np

from ti_cmax import so3
from ti_cmax.camera import Camera
from ti_cmax.config import SlamConfig, config_to_dict
from ti_cmax.errors import InputError
from ti_cmax.events import Events
from ti_cmax.progress import progress
from ti_cmax.spline import SO3Spline
from ti_cmax.trajectory import Trajectory

from .backend import SlidingWindowBackend
from .frontend import FrontendResult, FrontendRunner, as_chunks, downsampled
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

    def __init__(self, camera: Camera, config: SlamConfig, r_start_of):
        self.camera, self.config, self.r_start_of = camera, config, r_start_of
        self.backend: SlidingWindowBackend | None = None
        self.events_read = 0

    def __call__(self, chunks: Iterable[Events]) -> Iterator[Events]:
        q = int(self.config.backend.backend_event_sample_rate)
        for chunk in chunks:
            if len(chunk) == 0:
                continue
            if self.backend is None:
                t0 = float(chunk.t[0])
                self.backend = SlidingWindowBackend(self.config.backend, t0, self.r_start_of(t0))
                if self.config.loop.loop_closure:  # loop closure on revisits (pipelines/loop_closure.py)
                    self.backend.loop = LoopCloser(self.config.loop, self.backend)
            sub = chunk[(-self.events_read) % q::q] if q > 1 else chunk
            self.events_read += len(chunk)
            self.backend.push_events(sub.t, self.camera.bearings(sub.x, sub.y), complete_until=float(chunk.t[-1]))
            yield chunk


def _backend_report(backend: SlidingWindowBackend, wall: float) -> dict:
    optimized = [w for w in backend.windows if w.optimized]
    in_optimized = sum(w.num_events for w in optimized)
    return {
        "windows": len(backend.windows),
        "windows_optimized": len(optimized),
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
                      global_map=np.ones((h, w), np.float32), alpha=1.0)
    problem.cost_and_grad(ctrl)
    vote_map(b, np.eye(3)[None], w, h, batch_size=4, occupancy=(np.zeros(w, np.int32), np.zeros(h, np.int32)))
    return time.perf_counter() - tic


def run_slam(events_or_chunks, camera: Camera, config: SlamConfig = SlamConfig(), *,
             progress_total: float | None = None) -> SlamResult:
    """CMax-SLAM on an ``Events`` object, an iterable of time-ordered chunks, or a dataset (``iter_events``).

    The trajectory starts at the identity at the first event (the world frame is the first camera frame).
    """
    wall0 = time.perf_counter()
    derived = derived_summary(config, camera)
    config = resolve_config(config, camera)
    runner = FrontendRunner(camera, config.frontend)
    compile_s = runner.compile() + _compile_backend(config)
    feed = _BackendFeed(camera, config, lambda t0: np.eye(3))
    chunks = feed(as_chunks(events_or_chunks))
    r_src = np.eye(3)
    t_prev, w_prev = None, None
    backend_seconds = 0.0
    bar = progress(total=progress_total, desc="slam", unit="s")
    try:
        for packet in runner.slicer(downsampled(chunks, int(config.frontend.frontend_event_sample_rate))):
            omega = runner.process(packet)
            if t_prev is not None:
                r_src = r_src @ so3.exp(0.5 * (w_prev + omega) * (packet.t_ref - t_prev))
                bar.update(packet.t_ref - t_prev)
            t_prev, w_prev = packet.t_ref, omega
            feed.backend.push_source_poses([packet.t_ref], r_src[None])
            tic = time.perf_counter()
            while feed.backend.ready():
                feed.backend.step()
            backend_seconds += time.perf_counter() - tic
        if feed.backend is None:
            raise InputError("no events to process")
        tic = time.perf_counter()
        feed.backend.finish()
        backend_seconds += time.perf_counter() - tic
    finally:
        bar.close()
    backend = feed.backend
    frontend = runner.result()
    n = max(feed.events_read, 1)
    report = {
        "status": frontend.status,
        "method": "cmax-slam",
        "events_processed": int(feed.events_read),
        "wall_seconds": time.perf_counter() - wall0,
        "compile_seconds": compile_s,
        "frontend": frontend.summary(),
        "backend": _backend_report(backend, backend_seconds),
        # per event of the input stream, steady state (compilation apart)
        "us_per_event": {"frontend": runner.seconds * 1e6 / n, "backend": backend_seconds * 1e6 / n},
        "parameters": config_to_dict(config),
        "derived_parameters": derived,
        **({"loops": backend.loop.loops} if backend.loop is not None else {}),
    }
    trajectory = backend.trajectory(config.output.trajectory_rate)
    return SlamResult(backend.spline, trajectory, backend.map.raw, report, frontend, backend.windows)


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
