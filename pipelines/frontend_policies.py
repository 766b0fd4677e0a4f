"""The front-end's policies around the packet step: when a packet's optimum is trusted, and when it is noise.

Contrast maximisation always returns an optimum, also for events that do not constrain omega (a still camera, noise,
a packet far too small for the sensor): on a flat cost the optimiser stops anywhere. These rules decide, from the
optimum and a few evaluations at omega = 0, whether the events measure the motion:

- the score test (:func:`motion_score`) of omega = 0, on the packets where the optimum is doubtful
  (:func:`needs_score_test`), with a second chance over a sub-span for fast motions (:func:`fast_motion_span`);
- the gain check (:func:`gain_check_due`, :func:`is_suspect`) on an even sample of packets, for the run's status;
- lookbacks (:class:`LookbackTest`): a flat packet's longer past, so a motion too slow for one packet still counts,
  and a motion right after a flat packet is kept only if the longer span measures it too.
"""
from __future__ import annotations

from typing import Callable

import numpy as np

from ti_cmax.config import FrontendConfig
from ti_cmax.events import Events

from .motion import Motion

# The score test runs where the optimum moves the packet's farthest event by under SLOW_PX pixels (too little motion
# to stand out of the noise by itself) ...
SLOW_PX = 1.0
# ... or lies at least 1 px and JUMP_FRACTION of its own motion from the warm start: an optimiser wandering on a flat
# cost jumps by about its own size at every packet, while a smooth motion's optimum changes by a few %.
JUMP_FRACTION = 0.25
# A packet failing the score test although its optimum moves events by FAST_PX or more is tested again over the
# sub-span in which that motion is SUB_PX (with at least SUB_MIN_EVENTS events): at omega = 0 a fast motion's IWE is
# blurred flat over the whole packet, and the test loses its power there.
FAST_PX, SUB_PX, SUB_MIN_EVENTS = 20.0, 4.0, 500
# The carried BFGS inverse Hessian is dropped above this condition number: a collapsed direction would hold every
# later step along it at ~0 and keep the warm start's error.
BFGS_MAX_CONDITION = 1e3
# Lookbacks span LOOKBACK_FACTOR x, its square x, ... the packet's span; in a run of flat packets one of
# LOOKBACK_EVERY looks back (a lookback several packets long changes little from one packet to the next).
LOOKBACK_FACTOR = 4.0
LOOKBACK_EVERY = 4


def gain_check_due(packets_estimated: int, config: FrontendConfig) -> bool:
    """Whether this packet gets the gain check (1 of ``frontend_gain_check_every``): an even sample of the packets
    suffices for the run's status, and each check costs most of an evaluation."""
    return packets_estimated % int(config.frontend_gain_check_every) == 0


def is_suspect(moved: float, gain: float, config: FrontendConfig) -> bool:
    """A solution that moves the farthest event by >= 1 px but sharpens the IWE by less than
    ``frontend_min_contrast_gain`` over omega = 0: the events do not constrain omega (most such packets in a run:
    its status is "suspect")."""
    return bool(moved >= 1.0 and gain < 1.0 + config.frontend_min_contrast_gain)


def needs_score_test(moved: float, jump: float) -> bool:
    """Whether an optimum is doubtful enough for the score test: it moves events by under SLOW_PX, or lies far from
    the warm start (1 px and JUMP_FRACTION of its motion), as an optimiser on a flat cost does."""
    return moved < SLOW_PX or jump >= max(1.0, JUMP_FRACTION * moved)


def motion_score(g_zero, cov: np.ndarray) -> float:
    """Score statistic of omega = 0: g0^T S^-1 g0, with g0 the contrast gradient at omega = 0 and S its noise
    covariance (from the spread of its per-event terms). Where the events measure no motion it is about chi-square
    with 3 degrees of freedom, so a threshold on it bounds the rate of noise packets taken for a motion."""
    g = np.asarray(g_zero, float)
    if not np.all(np.isfinite(cov)):
        return np.inf  # too few events to tell: keep the optimum, as without the test
    try:
        return float(g @ np.linalg.solve(cov, g))
    except np.linalg.LinAlgError:  # no spread at all (no event in the image at omega = 0): nothing measured
        return 0.0 if not np.any(g) else np.inf


def fast_motion_span(events: Events, t_ref: float, moved: float) -> Events | None:
    """For a packet whose optimum moves events by FAST_PX or more: its events within the sub-span in which that
    motion is SUB_PX, for a second score test (None when not fast, or too few events there). At omega = 0 a fast
    packet's IWE is blurred flat over the whole motion and its gradient is noise; over a short sub-span the blur is
    small again and the test has its power (a stream starting at full speed has no warm start to fall back on)."""
    if moved < FAST_PX:
        return None
    half = float(np.max(np.abs(events.t - t_ref))) * SUB_PX / moved
    sub = events.slice_time(t_ref - half, t_ref + half)
    return sub if len(sub) >= SUB_MIN_EVENTS else None


class Lookback:
    """The recent events of the stream, for testing a flat packet's past for motion over a longer span.

    Holds the events of the last ``span`` seconds; each packet's new events are thinned to at most ``density``
    events per second (1 of k, even in the event index), so memory stays at most span x density events whatever
    the event rate. A lookback of that span is thinned again to the packet cap by the estimator."""

    def __init__(self, span: float, density: float):
        self.span, self.density = float(span), float(density)
        self._parts: list[Events] = []
        self._t_end = -np.inf

    def add(self, events: Events) -> None:
        """Append the events of a packet that are later than those held (packets overlap)."""
        new = events[int(events.index_at(self._t_end, side="right")):] if np.isfinite(self._t_end) else events
        if len(new) == 0:
            return
        start = self._t_end if np.isfinite(self._t_end) else float(new.t[0])
        k = int(np.ceil(len(new) / max(self.density * max(float(new.t[-1]) - start, 1e-6), 1.0)))
        self._t_end = float(new.t[-1])
        self._parts.append(new[(k // 2)::k] if k > 1 else new)
        while len(self._parts) > 1 and self._parts[0].t[-1] < self._t_end - self.span:
            self._parts.pop(0)

    def recent(self, length: float) -> Events:
        """The held events of the last ``length`` seconds (up to the last one added)."""
        if not self._parts:
            return Events.empty()
        held = Events.concatenate(self._parts) if len(self._parts) > 1 else self._parts[0]
        held = held[int(held.index_at(self._t_end - self.span)):]  # (joined, the parts no longer drop the oldest)
        self._parts = [held]
        return held[int(held.index_at(self._t_end - length)):]


class LookbackTest:
    """Score tests over a packet's recent past (``frontend_flat_lookback``), where one packet cannot tell:

    - a flat packet: is the camera still, or moving too slowly for one packet? A measured motion makes it SLOW: it
      keeps omega = 0 (a constant omega over a lookback is too coarse for the trajectory) but counts as moving, so
      the back-end refines its window;
    - a packet that measures a motion right after a flat one: a start, or a noise packet passing the score test by
      chance? Unless its lookback measures the motion too it is UNCONFIRMED (omega = 0).

    ``measures_motion(events, t_ref)`` is the estimator's score test over a set of events."""

    def __init__(self, config: FrontendConfig, measures_motion: Callable[[Events, float], bool]):
        # the shortest lookback (LOOKBACK_FACTOR x the minimum span) may hold a full packet cap of events
        cap = max(config.num_events_per_packet, config.frontend_max_packet_events)
        base = max(config.frontend_min_packet_span, config.dt_ang_vel)
        self.events = Lookback(config.frontend_flat_lookback, cap / (LOOKBACK_FACTOR * base))
        self.min_span = float(config.frontend_min_packet_span)
        self.measures_motion = measures_motion
        self.flat_run = 0  # flat packets in a row
        self._last_look = 0.0  # span of the run's last lookback that measured a motion (0: none)

    def confirm(self, events: Events, span: float, motion: Motion) -> tuple[Motion, float]:
        """The motion of a packet just estimated (MOVING or FLAT), given its past; and the span of the lookback that
        measured a motion (0: none). In a run of flat packets one of LOOKBACK_EVERY looks back, the others take
        its answer."""
        self.events.add(events)
        if motion is Motion.MOVING:
            looked = self._look_back(span) if self.flat_run else 0.0
            if not looked and self.flat_run:
                motion = Motion.UNCONFIRMED
        else:
            if self.flat_run % LOOKBACK_EVERY == 0:
                self._last_look = self._look_back(span)
            looked = self._last_look
        self.flat_run = self.flat_run + 1 if motion.flat else 0
        return (Motion.SLOW if motion is Motion.FLAT and looked else motion), looked

    def _look_back(self, span: float) -> float:
        """The score test over the events of the last 4x, 16x, ... the packet's span, up to the lookback's span.
        Returns the span of the first lookback that measures a motion (0: none; still as far as the events tell)."""
        length = LOOKBACK_FACTOR * max(span, self.min_span)
        covered = span
        while True:
            events = self.events.recent(min(length, self.events.span))
            if len(events) < 2 or events.duration <= 1.01 * covered:  # no events older than those already tried
                return 0.0
            if self.measures_motion(events, 0.5 * (float(events.t[0]) + float(events.t[-1]))):
                return float(events.duration)
            if length >= self.events.span:
                return 0.0
            covered, length = events.duration, length * LOOKBACK_FACTOR
