"""Is a tracker's motion consistent with the events? A contrast-maximization check for the filter baselines.

A tracker that feeds its own map (SMT) can drift or jump while every internal statistic (map support, polarity
agreement, covariance) still looks healthy: the map follows the wrong poses. The events themselves are an
independent witness: over a short window, warping them with the tracker's angular velocity gives a sharp image
only if that velocity is right. The check compares the contrast (the front-end's normalised IWE variance,
pipelines/frontend.py, same kernels) at the tracker's omega with the best contrast CG finds from there and from
the previous check's optimum. A ratio near 1 means the tracker's omega is a contrast maximum; the ratio falls as
the velocity error grows (measured on simulated EKF-SMT runs: >= 0.97 with errors below 0.15 rad/s, 0.84 at
0.8 rad/s, 0.3-0.5 at 3 rad/s; at ground truth 0.999-1.000).

Slow drift (``drift_horizon`` > 0): a steady velocity error below that size keeps every ratio above 0.95 yet
integrates into attitude drift (an EKF-SMT pan into new texture: speed 7 % low, ratios 0.97-0.99, 6 deg off in
0.5 s). Each check also gives the optimum omega_best (CG's, the front-end's estimate of the motion), so the drift
of the tracker against the events over a check is e = R (omega - omega_best) x interval (world frame). Over the
last ``drift_horizon`` s, split into ``drift_parts`` equal parts, tracking fails when the drift of EVERY part along
the horizon's total drift direction exceeds ``drift_min_deg``: the error must be steady, so a transient one (a
turn-back, which the map corrects later) or the optimum's own noise (its error changes sign from check to check)
does not count. Measured with 0.6 s, 3 parts, per part (max over each sequence): 0.03-0.63 deg on the 24 paper and
held-out benchmark sequences EKF-SMT tracks (abs 0.09-1.92 deg), 2.65 deg on the pan above. The threshold, 1.5 deg
per 0.2 s part, is a sustained 0.13 rad/s: about where the ratio test starts to see an error (0.15 rad/s above).
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
    the last ``checks`` windows is below ``min_ratio``, or by the slow-drift test (module doc; ``drift_horizon``
    0: off), which then returns the start of its horizon; ``failure`` says which. Windows with fewer events than
    the front-end's minimum event rate times ``span`` are skipped (nothing to judge).
    """

    def __init__(self, camera: Camera, t_start: float, interval: float, span: float, min_ratio: float,
                 checks: int, frontend: FrontendConfig = FrontendConfig(), drift_horizon: float = 0.0,
                 drift_parts: int = 3, drift_min_deg: float = 1.5):
        self.estimator = AngularVelocityEstimator(camera, frontend)
        self.interval, self.half, self.min_ratio = float(interval), 0.5 * float(span), float(min_ratio)
        self.min_events = max(int(self.estimator.config.frontend_min_event_rate * span), 100)
        self.next_centre = float(t_start) + self.half
        self.recent: deque = deque(maxlen=max(int(checks), 1))
        self.ratios: list[float] = []
        self.drift_horizon, self.drift_parts = float(drift_horizon), max(int(drift_parts), 1)
        self.drift_min = np.radians(float(drift_min_deg))
        self.drift: deque = deque()  # (window start, centre, world-frame drift vector in rad) of recent checks
        self.t_start = float(t_start)
        self.max_drift_deg = 0.0  # largest slow-drift statistic seen (report)
        self.failure = ""  # why the last failing update failed
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
            ratio, best = self.estimator.contrast_ratio(ev[i0:i1], tc, omega)
            self.seconds += time.perf_counter() - tic
            self.ratios.append(ratio)
            self.recent.append((tc - self.half, ratio))
            if len(self.recent) == self.recent.maxlen and np.mean([r for _, r in self.recent]) < self.min_ratio:
                failed = self.recent[0][0]
                self.failure = (f"motion inconsistent with events: contrast ratio "
                                f"{np.mean([r for _, r in self.recent]):.2f} < {self.min_ratio}")
            elif self.drift_horizon > 0:
                failed = self._drift(tc, poses[a] @ (omega - best) * self.interval)
        self._trim()
        return failed

    def _drift(self, tc: float, e: np.ndarray) -> float | None:
        """Slow-drift test (module doc) after the check centred at tc with drift e; the failing horizon's start."""
        h, k = self.drift_horizon, self.drift_parts
        self.drift.append((tc - self.half, tc, e))
        while self.drift and self.drift[0][1] <= tc - h:
            self.drift.popleft()
        if tc - h < self.t_start - 1e-9:  # the horizon must lie within tracking
            return None
        parts = np.zeros((k, 3))
        for _, c, v in self.drift:
            parts[min(int((c - (tc - h)) / h * k), k - 1)] += v
        total = parts.sum(0)
        norm = float(np.linalg.norm(total))
        if norm == 0.0:
            return None
        least = float(np.min(parts @ (total / norm)))
        self.max_drift_deg = max(self.max_drift_deg, float(np.degrees(least)))
        if least <= self.drift_min:
            return None
        self.failure = (f"slow drift: the tracker departs from the events' motion by over "
                        f"{np.degrees(self.drift_min):.1f} deg in each {h / k:.2f} s of the last {h:.2f} s "
                        f"({np.degrees(norm):.1f} deg in all)")
        return self.drift[0][0]

    def summary(self) -> dict:
        r = np.asarray(self.ratios)
        return {"checks": int(len(r)), "min_ratio": float(r.min()) if len(r) else None,
                "mean_ratio": float(r.mean()) if len(r) else None, "seconds": self.seconds,
                "max_drift_deg": self.max_drift_deg}


__all__ = ["MotionConsistencyCheck"]
