"""The rules around the back-end's window step (pipelines/backend.py): which windows get a BA, which control poses
it may move, how the first window fixes the world frame, what a window at the end of the stream covers, and when a
BA's optimum is a false maximum.

Each rule is a small function of plain values, so the window step itself reads as the paper's three steps.
"""
from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import numpy as np

TIME_EPS = 1e-9
EMPTY_WINDOWS_PER_FIT = 10  # windows without events fitted at once (fit_due)
# why a window gets no BA (WindowReport.no_ba)
FEW_EVENTS = "too few events"
STILL = "no motion measured over the window"  # every packet over it was still: the window is still
SKIPPED = "skipped by the real-time budget"
# what became of a window whose BA optimum departed beyond the check's bound (refit_outcome)
CONFIRMED = "confirmed"  # a local refit found the same maximum: the optimum is kept
REFITTED = "refitted"  # the local refit found a maximum within the bound: its optimum replaces the first one
KEPT_INITIALISATION = "initialisation kept"  # the refit departed beyond the bound too, elsewhere: no optimum is trusted
# departure_bound: the accepted corrections of this many preceding windows give a source's typical one, and a
# correction up to TYPICAL_FACTOR times their median is within its spread (for Gaussian errors the largest magnitude
# in a thousand windows is 2.6 (three axes) to 4.9 (one axis) times their median)
RECENT_WINDOWS = 20
TYPICAL_FACTOR = 5.0


@dataclass(frozen=True)
class Window:
    """One window [t0, t1] of the sliding-window BA; ``final``: the stream's last, which settles every event left."""

    t0: float
    t1: float
    final: bool = False

    def settle_end(self, stride: float) -> float:
        """Partial windows: a window settles its first stride; the final one every event left."""
        return self.t1 + 1.0 if self.final else self.t0 + stride


@dataclass(frozen=True)
class WindowBudget:
    """What the real-time controller (pipelines/realtime.py) grants a window's BA; the default is the offline
    computation. Values out of range raise ValueError."""

    ba_cap: int | None = None  # BA events at most (None: backend_max_window_events); 0 skips the BA
    ba_every: int = 1  # the BA runs on 1 of ba_every windows; the others keep their initialisation, as ba_cap = 0
    ba_budget: float | None = None  # wall seconds after which the BA starts no iteration (None: no limit)
    loop_idle_only: bool = False  # the loop closer's work in flight waits for the worker's idle time (no slice per window)

    def __post_init__(self):
        if int(self.ba_every) != self.ba_every or self.ba_every < 1:
            raise ValueError(f"ba_every must be an integer >= 1, got {self.ba_every!r}")
        if self.ba_cap is not None and (int(self.ba_cap) != self.ba_cap or self.ba_cap < 0):
            raise ValueError(f"ba_cap must be None or an integer >= 0, got {self.ba_cap!r}")
        if self.ba_budget is not None and not self.ba_budget >= 0:
            raise ValueError(f"ba_budget must be None or >= 0 seconds, got {self.ba_budget!r}")
        object.__setattr__(self, "ba_cap", None if self.ba_cap is None else int(self.ba_cap))
        object.__setattr__(self, "ba_every", int(self.ba_every))
        object.__setattr__(self, "ba_budget", None if self.ba_budget is None else float(self.ba_budget))
        object.__setattr__(self, "loop_idle_only", bool(self.loop_idle_only))


FULL_BUDGET = WindowBudget()


def partial_window_end(t0: float, t1: float, last_event: float, last_source: float) -> float:
    """Partial windows: the stream's last window ends at its last event or source pose (at most a full window
    after t0), so the final step covers what is left and no more."""
    return max(t0 + 1e-6, min(t1, max(last_event, last_source)))


def motion_start(moves: deque, source_t: np.ndarray, window: Window) -> float | None:
    """Still windows: the first time in the window from which the source measured a motion (``moves``: spans
    (a, b) over which it did); None when it measured none over the whole window. Events without motion hold nothing
    a BA could refine (noise, flicker) and a BA would fit the poses to them, so such a window gets no BA and a window
    that starts still keeps its still part's poses. Forgets the spans before the window (windows advance in time).
    Until the source reaches the window's end the window counts as moving, except the final one."""
    while moves and moves[0][1] < window.t0:
        moves.popleft()
    if not len(source_t) or (source_t[-1] < window.t1 and not window.final):
        return window.t0
    starts = [a for a, b in moves if a < window.t1 and b > window.t0]
    return max(window.t0, min(starts)) if starts else None


def why_no_ba(num_events: int, window: Window, moving_from: float | None, budget: WindowBudget,
              windows_done: int, cfg) -> str | None:
    """Why the window gets no BA (None: it gets one): too few events for the variance to mean anything (fewer
    than two batches or below backend_min_ev_rate), no motion measured over it (STILL), or the real-time
    budget skips it (ba_cap 0, or not 1 of ba_every windows)."""
    rate = num_events / max(window.t1 - window.t0, 1e-9)
    if num_events < 2 * cfg.event_batch_size or rate < cfg.backend_min_ev_rate:
        return FEW_EVENTS
    if moving_from is None:
        return STILL
    if budget.ba_cap == 0 or windows_done % max(1, budget.ba_every) > 0:
        return SKIPPED
    return None


def fit_due(num_events: int, window: Window, anchor_t: float | None, stride: float) -> bool:
    """Windows without events (a pause of the stream) are fitted together with a later one: one fit per
    EMPTY_WINDOWS_PER_FIT strides of a pause instead of one per window, and the source poses kept stay bounded."""
    return bool(num_events) or window.final or anchor_t is None or \
        window.t1 > anchor_t + EMPTY_WINDOWS_PER_FIT * stride


def first_free_pose(knots: np.ndarray, t0: float, moving_from: float | None, cfg) -> int:
    """The first control pose the BA may move: the first with knot time >= t0, never the very first (it anchors
    the world frame), and past the still start of a window (a control pose shapes R(t) within half its support
    of its knot, and the still part keeps its poses)."""
    first_free = max(int(np.searchsorted(knots, t0 - TIME_EPS, side="left")), 1)
    if moving_from is not None and moving_from > t0:
        reach = 0.5 * (cfg.spline_degree + 1) * cfg.dt_knots
        first_free = max(first_free, int(np.searchsorted(knots, moving_from - reach, side="right")))
    return first_free


def gauge_free(t0: float, t_start: float, first_free: int) -> bool:
    """First-window gauge: in the first window only the first control pose holds the orientation (no global map
    yet), so the BA's common rotation of the free poses is projected out of its step (on sparse scenes the map's
    sampling would reward turning them all); poses held still hold the orientation themselves."""
    return t0 <= t_start + TIME_EPS and first_free == 1


def gauge_fix(spline, t_start: float, r_start: np.ndarray) -> np.ndarray | None:
    """First-window gauge: the left rotation that makes R(t_start) = r_start exactly after the first window's BA
    (the world frame is the camera's at the first event); None when it holds already (a linear spline). A cubic
    R(t_start) also depends on the next control poses, which the BA moves; the window's contrast does not change
    when the whole trajectory turns, so the BA's optimum is kept, in the right frame."""
    r_at_start = spline.evaluate(t_start)[0]
    if np.array_equal(r_at_start, r_start):
        return None
    return r_start @ r_at_start.T


def even_sample_index(n: int, cap: int) -> np.ndarray | None:
    """The rows of at most ``cap`` of ``n`` events (negative: all), every (n / cap)-th: even in time, and over the
    image in proportion to where the events are. None: all of them."""
    if cap < 0 or n <= cap:
        return None
    return ((np.arange(cap) + 0.5) * (n / cap)).astype(np.int64)


def false_maximum(max_correction: float, cfg) -> str | None:
    """Rejected windows: a BA that moves the trajectory at the window's events by more than backend_max_correction
    found a false maximum (e.g. a map too coarse for the sensor); the window keeps its initialisation and is
    refitted as a window without a BA. Returns the reason, None when the correction is within the bound."""
    if max_correction > cfg.backend_max_correction:
        return (f"correction {np.degrees(max_correction):.2f} deg beyond backend_max_correction "
                f"({np.degrees(cfg.backend_max_correction):.2f} deg)")
    return None


def departure_bound(width: int, blur_sigma: float, recent=()) -> float:
    """The false-maximum check's bound (rad): the reach of one event's vote in the blurred map, 3 sigma of the blur
    plus the bilinear vote's pixel, as an angle on a map ``width`` pixels around: (3 sigma + 1) 2 pi / width.
    An optimum that moves the trajectory by more than this from the initialisation has carried the window's events
    beyond where their votes at the initialisation reached: onto other structure, a different alignment rather than a
    refinement of the initialisation, which a local optimiser's long step (a carried inverse Hessian, a step cap of
    several pixels) can reach past the maximum nearest to it. The front-end's motion over a window is off by far
    less on the data it measures well: its packets are sharp to a fraction of a sensor pixel, and the reach is 4 map
    pixels with the default blur, 2.7 sensor pixels at the default map scale. A poorer initialising trajectory (a
    refined baseline, IMU dead reckoning with a large bias) is off by more in every window; ``recent``, the accepted
    corrections of the last windows (rad), raises the bound to TYPICAL_FACTOR times their median, so that only a
    correction far out of the source's own spread is checked."""
    reach = (3.0 * float(blur_sigma) + 1.0) * 2.0 * np.pi / float(width)
    return max(reach, TYPICAL_FACTOR * float(np.median(recent))) if len(recent) else reach


def departs(correction: float, bound: float) -> str | None:
    """The check of a window's BA optimum against what the window was initialised from: the previous windows'
    optimum (the control poses before the window stay fixed, so the initialisation continues it) followed by the
    front-end's integrated angular velocity. An optimum that moves the trajectory at the window's events by more than
    ``bound`` (departure_bound) from it bends away from both: suspect of a false maximum. Returns the reason, None
    when it passes."""
    if correction > bound:
        return (f"correction {np.degrees(correction):.2f} deg beyond the check's bound "
                f"({np.degrees(bound):.2f} deg)")
    return None


def refit_outcome(refit_correction: float, between: float, bound: float) -> str:
    """What a suspect window keeps after its local refit (started afresh from the initialisation with steps within
    the reach of a vote, so that it climbs to the maximum nearest to it); the figures are the largest changes of the
    trajectory at the window's events (rad). The first optimum when the refit lands within ``bound`` of it
    (``between``: the same maximum, the initialisation was that far off; CONFIRMED); the refit's optimum when its
    correction is within ``bound`` (REFITTED); else the initialisation: the events offer maxima far from it in more
    than one place, and none of them is trusted over it (KEPT_INITIALISATION, as a rejected window)."""
    if between <= bound:
        return CONFIRMED
    if refit_correction <= bound:
        return REFITTED
    return KEPT_INITIALISATION


def correction_samples(s: np.ndarray, u: np.ndarray, most: int = 256):
    """Where the BA's correction is measured: the trajectory at 256-511 of the batches' times, evenly, and the last
    (the difference of two splines is smooth within a knot interval)."""
    every = max(1, len(s) // most)
    return np.append(s[::every], s[-1]), np.append(u[::every], u[-1])
