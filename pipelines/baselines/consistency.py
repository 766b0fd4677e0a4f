"""Is a tracker's motion consistent with the events? A contrast-maximization check for the filter baselines.

A tracker that feeds its own map (SMT) can drift or jump while every internal statistic (map support, polarity
agreement, covariance) still looks healthy: the map follows the wrong poses. The events themselves are an
independent witness: over a short window, warping them with the tracker's angular velocity gives a sharp image
only if that velocity is right. The check compares the contrast (the front-end's normalised IWE variance,
pipelines/frontend.py, same kernels) at the tracker's omega with the best contrast CG finds from there and from
the previous check's optimum. A ratio near 1 means the tracker's omega is a contrast maximum; the ratio falls as
the velocity error grows (measured on simulated EKF-SMT runs: >= 0.97 with errors below 0.15 rad/s, 0.84 at
0.8 rad/s, 0.3-0.5 at 3 rad/s; at ground truth 0.999-1.000).
"""
from __future__ import annotations

import time
from collections import deque

import numpy as np

from ti_cmax import so3
from ti_cmax.camera import Camera
from ti_cmax.config import FrontendConfig
from ti_cmax.events import Events

from ..frontend import AngularVelocityEstimator


class MotionConsistencyCheck:
    """Contrast ratios of a tracker's angular velocity over windows of ``span`` s centred every ``interval`` s.

    Streaming: ``update(events, times, poses, t_done)`` takes the events and tracker poses that are new since the
    last call (it keeps only the tail it still needs), checks every window that ends by ``t_done`` and returns
    the start of the first window of a failing run (None while consistent): tracking fails when the mean ratio of
    the last ``checks`` windows is below ``min_ratio``. Windows with fewer events than the front-end's minimum
    event rate times ``span`` are skipped (nothing to judge).
    """

    def __init__(self, camera: Camera, t_start: float, interval: float, span: float, min_ratio: float,
                 checks: int, frontend: FrontendConfig = FrontendConfig()):
        self.estimator = AngularVelocityEstimator(camera, frontend)
        self.interval, self.half, self.min_ratio = float(interval), 0.5 * float(span), float(min_ratio)
        self.min_events = max(int(self.estimator.config.frontend_min_event_rate * span), 100)
        self.next_centre = float(t_start) + self.half
        self.recent: deque = deque(maxlen=max(int(checks), 1))
        self.ratios: list[float] = []
        self.seconds = 0.0  # spent checking (part of the tracker's wall time)
        self._events: list[Events] = []
        self._times: list[np.ndarray] = []
        self._poses: list[np.ndarray] = []

    def compile(self) -> float:
        return self.estimator.compile()

    def _trim(self) -> None:
        keep_from = self.next_centre - self.half
        while len(self._events) > 1 and self._events[0].t[-1] < keep_from:
            self._events.pop(0)
        while len(self._times) > 1 and self._times[1][0] <= keep_from:  # keep the last pose before keep_from
            self._times.pop(0)
            self._poses.pop(0)

    def update(self, events: Events, times: np.ndarray, poses: np.ndarray, t_done: float) -> float | None:
        """New ``events`` and tracker ``times`` / ``poses`` (world_from_camera), the poses valid up to ``t_done``."""
        if len(events):
            self._events.append(events)
        if len(times):
            self._times.append(np.asarray(times, np.float64))
            self._poses.append(np.asarray(poses, np.float64))
        if self.next_centre + self.half > t_done or not self._times:
            self._trim()
            return None
        ev = Events.concatenate(self._events) if len(self._events) > 1 else self._events[0]
        times, poses = np.concatenate(self._times), np.concatenate(self._poses)
        self._events, self._times, self._poses = [ev], [times], [poses]
        failed = None
        while failed is None and self.next_centre + self.half <= t_done:
            tc = self.next_centre
            self.next_centre += self.interval
            a = int(np.searchsorted(times, tc - self.half, side="left"))
            b = int(np.searchsorted(times, tc + self.half, side="right")) - 1
            i0, i1 = np.searchsorted(ev.t, [tc - self.half, tc + self.half])
            if b <= a or times[b] <= times[a] or i1 - i0 < self.min_events:
                continue
            omega = so3.log(poses[a].T @ poses[b]) / (times[b] - times[a])  # camera frame (right increment)
            tic = time.perf_counter()
            ratio, _ = self.estimator.contrast_ratio(ev[i0:i1], tc, omega)
            self.seconds += time.perf_counter() - tic
            self.ratios.append(ratio)
            self.recent.append((tc - self.half, ratio))
            if len(self.recent) == self.recent.maxlen and np.mean([r for _, r in self.recent]) < self.min_ratio:
                failed = self.recent[0][0]
        self._trim()
        return failed

    def summary(self) -> dict:
        r = np.asarray(self.ratios)
        return {"checks": int(len(r)), "min_ratio": float(r.min()) if len(r) else None,
                "mean_ratio": float(r.mean()) if len(r) else None, "seconds": self.seconds}


__all__ = ["MotionConsistencyCheck"]
