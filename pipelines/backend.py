"""Sliding-window CMax bundle adjustment (paper Sec. III-B, III-C2): the back-end of CMax-SLAM.

The back-end owns the continuous trajectory (an SO(3) spline with control poses every ``dt_knots``) and the
global panoramic map I_G. It is fed two streams in time order:

* events (times and undistorted bearings), and
* *source poses*: any trajectory to initialize new spline segments from (the front-end's integrated angular
  velocity online; a given trajectory for offline refinement; IMU dead reckoning). Only relative rotations
  of the source are used: each new segment starts from the last optimized pose (Sec. III-C2, Initialization).

For every window [T, T + backend_time_window_size] (T advancing by backend_sliding_window_stride):
1. initialize the control poses that the window adds by lift-solve-retract on the re-anchored source poses;
2. if the event rate is at least backend_min_ev_rate, maximize Var(B(I_L) + alpha B(I_G)) (Eq. 18) over the
   control poses with knot time >= T (earlier ones are fixed), with alpha = rho(I_L) / rho(I_G) (Eq. 16-17)
   computed once from the initial I_L, on left increments R_k <- exp(x_k) R_k^0, by BFGS whose inverse Hessian
   carries over from the previous window (``backend_optimizer``; or the reference's Fletcher-Reeves CG);
3. settle the events of [T, T + stride) into I_G with the refined poses (optionally freezing map pixels that
   have been observed for max_update_time seconds).
"""
from __future__ import annotations

import dataclasses
import sys
import time
from collections import deque
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Callable

import numpy as np

from ti_cmax import so3
from ti_cmax.config import BackendConfig
from ti_cmax.kernels.pano import (
    PanoIWE, VoteWork, batch_mid_times, blur_radius, blur_region, column_selector, revote, touched_region, vote_map,
)
from ti_cmax.spline import SO3Spline
from ti_cmax.trajectory import Trajectory

from . import backend_policies as policy
from .backend_policies import FULL_BUDGET, TIME_EPS, Window, WindowBudget
from .optim import bfgs, fletcher_reeves

_TIME_EPS = TIME_EPS


@dataclass
class WindowReport:
    """What happened in one window (kept for the report and for tests)."""

    t_start: float
    t_end: float
    num_events: int
    optimized: bool
    alpha: float
    events_used: int = 0  # events the BA used (all, or an even sample of backend_max_window_events)
    iterations: int = 0
    evaluations: int = 0
    variance_before: float = 0.0
    # the last evaluated one: a last BFGS step taken unevaluated was predicted to change it by under half
    # backend_cg_rel_cost_tol (relative)
    variance_after: float = 0.0
    max_correction: float = 0.0  # largest change of the trajectory at the window's events (rad)
    # the window kept its initialisation: its BA's optimum was a false maximum (the correction exceeded
    # backend_max_correction, or it failed the check and so did its refit)
    rejected: bool = False
    false_maximum: str | None = None  # why the BA's optimum was judged a false maximum; None: it was not
    refitted: bool = False  # that optimum was replaced by a local refit's (backend_policies.refit_outcome)
    confirmed: bool = False  # the optimum departed beyond the check's bound and a local refit found the same maximum
    seconds: float = 0.0
    no_ba: str | None = None  # why the window got no BA (backend_policies.why_no_ba); None: it got one
    cut_short: bool = False  # BA stopped at the real-time controller's time budget (ba_budget): its best point kept
    done_at: float = 0.0  # time.monotonic() when the window completed (the same clock in every process)
    ba_seconds: float = 0.0  # wall time of the BA (part of ``seconds``)
    busy_seconds: float | None = None  # worker process: wall time it worked since the previous window (not waiting)

    @property
    def still(self) -> bool:
        """No motion was measured over the window (no BA: its events hold nothing to refine)."""
        return self.no_ba == policy.STILL

    @property
    def skipped(self) -> bool:
        """The real-time budget skipped the window's BA (its initialisation kept)."""
        return self.no_ba == policy.SKIPPED


class StageClock:
    """CPU and wall seconds per named stage, for the report's per-stage costs (``with clock("ba"): ...``)."""

    def __init__(self):
        self.cpu: dict[str, float] = {}
        self.wall: dict[str, float] = {}

    @contextmanager
    def __call__(self, name: str | None):
        if name is None:  # an untimed stage (a no-op observer's)
            yield
            return
        wall, cpu = time.perf_counter(), time.process_time()
        try:
            yield
        finally:
            self.wall[name] = self.wall.get(name, 0.0) + time.perf_counter() - wall
            self.cpu[name] = self.cpu.get(name, 0.0) + time.process_time() - cpu

    def summary(self) -> dict:
        return {"cpu_seconds": dict(self.cpu), "wall_seconds": dict(self.wall)}


class _Buffer:
    """Growing column buffer (times + bearings) that drops its settled head cheaply: the bearings are kept one row per
    coordinate, (3, capacity) float32, the layout the BA's and the settle's kernels read (kernels/pano.py): a window's
    events reach them by a row-wise copy (or a take of a sample), not a transposition. The columns live in arrays with
    room past the end, a push writes only its own events in, and dropping the head moves a start index. Once the
    settled head is as large as the live part, the live part moves to the front (in place when no view of the arrays
    is held, else into new ones): at most one copy per event pushed, and the rows ever written stay within two live
    parts (a row written for the first time costs a page fault and the zeroing of its page: more than a copy). Arrays
    are sized at their first growth past a millisecond of events for ``GROWTH_SPANS`` ``horizon``s (seconds: the
    span the buffer typically holds) at the event rate seen, so they rarely grow again: np.empty's rows cost nothing
    until written. Reads are views, so a window's read costs nothing in proportion to the buffer."""

    GROWTH_SPANS = 8
    MIN_RATE_SPAN = 1e-3  # seconds of events before their rate sizes the arrays

    def __init__(self, horizon: float = 0.0):
        self.horizon = float(horizon)
        self._tt, self._bb = np.zeros(0), np.zeros((3, 0), np.float32)
        self._start = self._end = 0

    @property
    def t(self) -> np.ndarray:
        return self._tt[self._start:self._end]

    @property
    def b(self) -> np.ndarray:
        """The live bearings, (3, n): a view (rows ``capacity`` apart)."""
        return self._bb[:, self._start:self._end]

    def push(self, t: np.ndarray, b: np.ndarray) -> None:
        """Append copies of times ``t`` and bearings ``b`` (n, 3) (a live source may refill its arrays after the
        call)."""
        n = len(t)
        if not n:
            return
        tt, bb, row = self.reserve(n)
        tt[row:row + n], bb[:, row:row + n] = t, np.asarray(b).T
        self.commit(n)

    def prepare(self, rate: float) -> None:
        """Arrays sized for a stream of ``rate`` events/s as its first growth would size them, with the rows a steady
        stream writes (two ``horizon``s: the live part, then its move to the front) written once now. A row's first
        write is a page fault, ~0.6 us per 4 kB and ~10 on a virtual machine whose host reclaims the guest's free
        memory: a real-time replay pays them here, before its clock starts, not in its first seconds. Nothing is
        done once events are held, without a horizon or a rate, or when the system cannot map the arrays."""
        if self._end > 0 or self.horizon <= 0 or not rate > 0:
            return
        cap = self._rate_capacity(rate)
        if cap <= len(self._tt):
            return
        try:
            tt, bb = self._new_arrays(cap)
        except MemoryError:
            return
        touched = min(cap, int(2 * self.horizon * rate))
        tt[:touched], bb[:, :touched] = 0.0, 0.0
        self._tt, self._bb, self._start, self._end = tt, bb, 0, 0

    def _rate_capacity(self, rate: float) -> int:
        """Rows for ``GROWTH_SPANS`` horizons of a stream of ``rate`` events/s (at most 2^31 - 1: the gather kernel's
        rows are 32-bit)."""
        return min(int(self.GROWTH_SPANS * self.horizon * rate), 2 ** 31 - 1)

    @staticmethod
    def _new_arrays(cap: int) -> tuple[np.ndarray, np.ndarray]:
        """Unwritten time (cap,) and bearing (3, cap) arrays (MemoryError when the system cannot map them)."""
        return np.empty(cap), np.empty((3, cap), np.float32)

    def reserve(self, n: int) -> tuple[np.ndarray, np.ndarray, int]:
        """Room for ``n`` events past the end: (the whole time (capacity,) and bearing (3, capacity) arrays, the row
        (column of the bearings) where they go), for a writer that fills them in place; ``commit`` then counts them
        in."""
        live = self._end - self._start
        if self._start >= live and self._start and live + n <= len(self._tt) \
                and sys.getrefcount(self._tt) == sys.getrefcount(self._bb) == 2:
            # no view of the arrays outside (only this attribute and the call's argument refer to them, as
            # ndarray.resize checks): the live part moves to the front in place (no overlap), into rows already
            # faulted in
            self._tt[:live], self._bb[:, :live] = self.t, self.b
            self._start, self._end = 0, live
        if self._end + n > len(self._tt):
            cap = max(2 * (live + n), 1024)
            span = float(self._tt[self._end - 1] - self._tt[self._start]) if live > 1 else 0.0
            if self.horizon > 0 and span >= self.MIN_RATE_SPAN:
                cap = max(cap, self._rate_capacity(live / span))
            cap = max(min(cap, 2 ** 31 - 1), live + n)  # (the gather kernel's rows are 32-bit)
            try:
                tt, bb = self._new_arrays(cap)
            except MemoryError:  # a rate estimate beyond what the system maps: room for twice what is needed
                tt, bb = self._new_arrays(2 * (live + n))
            tt[:live], bb[:, :live] = self.t, self.b
            self._tt, self._bb, self._start, self._end = tt, bb, 0, live
        return self._tt, self._bb, self._end

    def commit(self, n: int) -> None:
        """Count in the ``n`` events written at the row ``reserve`` gave."""
        if self._end + n > len(self._tt):
            raise ValueError(f"{n} events committed past the reserved room")
        self._end += n

    def drop_before(self, t: float) -> None:
        self._start += int(np.searchsorted(self.t, t, side="left"))

    def range(self, t0: float, t1: float, include_end: bool = False) -> tuple[np.ndarray, np.ndarray]:
        """Views of the events in [t0, t1) (or [t0, t1]): times (m,) and bearings (3, m). They stay valid: the
        buffer never writes where a view can look (pushes go past the end; a full buffer moves to new arrays)."""
        times = self.t
        i0 = int(np.searchsorted(times, t0, side="left"))
        i1 = int(np.searchsorted(times, t1, side="right" if include_end else "left"))
        return times[i0:i1], self.b[:, i0:i1]


def event_buffer(config: BackendConfig, rate: float | None = None) -> _Buffer:
    """The back-end's event buffer: its horizon a window and a stride; ``rate`` (events/s): prepared for it."""
    buffer = _Buffer(config.backend_time_window_size + config.backend_sliding_window_stride)
    if rate is not None:
        buffer.prepare(rate)
    return buffer


def _largest_angle(r_a: np.ndarray, r_b: np.ndarray) -> float:
    """The largest angle between two trajectories sampled at the same times, (n, 3, 3) each (rad)."""
    return float(np.max(so3.geodesic_angle(r_a, r_b)))


def _sum_and_squares(x: np.ndarray) -> tuple[float, float]:
    """(sum, sum of squares) of a float32 array, in float64 (einsum: a matrix product would call BLAS, whose
    threads spin on the other core after each call)."""
    y = x.astype(np.float64).reshape(-1)
    return float(y.sum()), float(np.einsum("i,i->", y, y))


class GlobalMap:
    """The global panoramic map I_G, its blur B(I_G) and the sums Eq. (16)-(18) need, kept up to date region by
    region: settling a stride of events costs in proportion to the events and the area they touch, never to the
    whole map (which matters for large maps: 8192x4096 is 33 M pixels).

    Optional pixel freezing (Sec. III-C2): a pixel stops accumulating ``max_update_time`` seconds after it was
    first observed (observation time only counts while the camera moves).
    """

    def __init__(self, width: int, height: int, sigma: float, lambda0: float, max_update_time: float | None = None,
                 downsample: int = 1):
        if width % downsample or height % downsample:
            raise ValueError(f"a {width} x {height} map cannot be downsampled by {downsample}")
        self.width, self.height, self.sigma, self.lambda0 = width, height, sigma, lambda0
        self.downsample = int(downsample)
        self.raw = np.zeros((height, width), np.float32)
        self._ba_raw = None if downsample == 1 else np.zeros(self.ba_size[::-1], np.float32)
        self.blurred = np.zeros(self.ba_size[::-1], np.float32)  # B(I_G) on the BA's map
        self.g_sum = self.g_sq = 0.0  # sums of B(I_G) and B(I_G)^2
        self.n_events = self.area = 0.0  # sum of I_G and its event area sum(1 - exp(-I_G / lambda0)) (BA's map)
        self.max_update_time = max_update_time
        self.first_seen = None if max_update_time is None else np.full((height, width), np.inf, np.float32)
        self._scratch = np.zeros((height, width), np.float32)  # stays zero between calls
        self._occ = (np.zeros(width, np.int32), np.zeros(height, np.int32))

    @property
    def ba_size(self) -> tuple[int, int]:
        """(width, height) of the map the BA reads: the output map's, ``downsample`` times coarser."""
        return self.width // self.downsample, self.height // self.downsample

    @property
    def ba_raw(self) -> np.ndarray:
        """I_G on the BA's map: the output map itself, or its re-voted coarse copy (kernels.pano.revote)."""
        return self.raw if self._ba_raw is None else self._ba_raw

    @property
    def density(self) -> float:
        """rho(I_G) = N_e / area (Eq. 16); 0 while empty."""
        return self.n_events / self.area if self.area > 0 else 0.0

    def _take_votes(self, bearings, rotations, batch_size, margin, weight):
        """Vote into the scratch map and take the votes (times weight) of the touched region (plus margin) out of
        it, leaving it zero: (rows, cols, sel, votes) with sel the region's index (slices, i.e. views, unless it
        straddles the seam), or None when no vote landed."""
        for occ in self._occ:
            occ[:] = 0
        vote_map(bearings, rotations, self.width, self.height, batch_size=batch_size, out=self._scratch,
                 occupancy=self._occ)
        region = touched_region(*self._occ, margin)
        if region is None:
            return None
        rows, cols = region
        sel = (rows, column_selector(cols))
        votes = self._scratch[sel]
        votes = votes.copy() if isinstance(sel[1], slice) else votes  # a view would be cleared below
        if weight != 1.0:
            votes *= np.float32(weight)
        self._scratch[sel] = 0
        return rows, cols, sel, votes

    def add(self, bearings, rotations, batch_size: int, t_now: float, moving: bool = True,
            weight: float = 1.0) -> None:
        """Vote events (per-batch rotations) into I_G and update B(I_G), the sums and the density. ``weight``
        scales the votes (a subsample standing for more events, as when loop closure rebuilds the map)."""
        taken = self._take_votes(bearings, rotations, batch_size, blur_radius(self.sigma), weight)
        if taken is not None:
            self._accumulate(*taken, t_now, moving)

    def add_votes(self, r0: int, cols: np.ndarray, votes: np.ndarray, t_now: float, moving: bool = True) -> None:
        """Add a local map of votes (bh, bw) float32 on rows [r0, r0 + bh) and columns ``cols`` (modulo the width),
        as ``PanoIWE.votes`` gives it (its window holds every vote plus the blur radius, as B(I_G)'s update needs)."""
        rows = slice(int(r0), int(r0) + len(votes))
        self._accumulate(rows, cols, (rows, column_selector(cols)), votes, t_now, moving)

    def _accumulate(self, rows: slice, cols: np.ndarray, sel, votes: np.ndarray, t_now: float, moving: bool) -> None:
        """I_G += votes on the region (rows, cols) = sel, then B(I_G), the sums and the event area there (on the BA's
        map: the region re-voted onto it when it is coarser)."""
        if self.first_seen is not None:
            seen = self.first_seen[sel]
            if moving:
                seen = np.minimum(seen, np.where(votes > 0, np.float32(t_now), np.float32(np.inf)))
                self.first_seen[sel] = seen
            votes = np.where((t_now - seen) < self.max_update_time, votes, 0).astype(np.float32)
        if self._ba_raw is not None:
            self.raw[sel] += votes  # (columns of a region are distinct: a gathered += scatters once per pixel)
            rows, cols, votes = self._coarse_region(rows, cols, votes)
            sel = (rows, column_selector(cols))
        self._accumulate_ba(rows, cols, sel, votes)

    def _coarse_region(self, rows: slice, cols: np.ndarray, votes: np.ndarray):
        """A region's votes re-voted onto the BA's coarser map, grown by its blur radius (B(I_G) changes there)."""
        wc, hc = self.ba_size
        r = blur_radius(self.sigma)
        rr, cc, v = revote(votes, rows.start, cols, self.downsample, self.width, self.height)
        top, bottom = max(rr.start - r, 0), min(rr.stop + r, hc)
        if len(cc) + 2 * r >= wc:
            out = np.zeros((bottom - top, wc), np.float32)
            out[rr.start - top:rr.stop - top][:, cc] = v
            return slice(top, bottom), np.arange(wc), out
        out = np.zeros((bottom - top, len(cc) + 2 * r), np.float32)
        out[rr.start - top:rr.stop - top, r:r + len(cc)] = v
        return slice(top, bottom), (int(cc[0]) - r + np.arange(out.shape[1])) % wc, out

    def _accumulate_ba(self, rows: slice, cols: np.ndarray, sel, votes: np.ndarray) -> None:
        """I_G += votes on the BA's map, then B(I_G), the sums and the event area on the region."""
        contiguous = isinstance(sel[1], slice)
        raw = self.ba_raw
        old_raw = raw[sel].copy() if contiguous else raw[sel]  # (a gather is a copy)
        if contiguous:
            raw[sel] += votes
            new_raw = raw[sel]
        else:
            new_raw = old_raw + votes
            raw[sel] = new_raw
        self.n_events += float(votes.sum(dtype=np.float64))
        # event area: sum of exp(-old / lambda0) - exp(-new / lambda0) over the region (exactly 0 where no vote
        # landed), the exponentials in float32 (vectorised: far cheaper than gathering the voted pixels for float64
        # ones; the sum in float64)
        scale = np.float32(-1.0 / self.lambda0)
        self.area += float(np.sum(np.exp(old_raw * scale) - np.exp(new_raw * scale), dtype=np.float64))
        old_sums = _sum_and_squares(blur_region(raw, self.blurred, rows, cols, self.sigma))
        new_sums = _sum_and_squares(self.blurred[sel])
        self.g_sum += new_sums[0] - old_sums[0]
        self.g_sq += new_sums[1] - old_sums[1]

    def set_raw(self, raw: np.ndarray) -> None:
        """Replace I_G by ``raw`` ((h, w) float32, taken over) and recompute B(I_G), its sums, N_e and the event area
        at once, on the rows holding votes (loop closure's rebuild: one blur instead of one per stride). Without
        pixel freezing only (its first-seen times need the strides in time order)."""
        if self.first_seen is not None:
            raise ValueError("set_raw: not with pixel freezing (settle the strides in order instead)")
        self.raw = np.ascontiguousarray(raw, dtype=np.float32)
        if self._ba_raw is not None:
            self._ba_raw = revote(self.raw, 0, np.arange(self.width), self.downsample, self.width, self.height)[2]
        ba = self.ba_raw
        self.blurred = np.zeros_like(ba)
        rows = np.flatnonzero(ba.any(axis=1))
        self.g_sum = self.g_sq = self.n_events = self.area = 0.0
        if len(rows) == 0:
            return
        band = slice(max(int(rows[0]) - blur_radius(self.sigma), 0),
                     min(int(rows[-1]) + blur_radius(self.sigma) + 1, ba.shape[0]))
        blur_region(ba, self.blurred, band, np.arange(ba.shape[1]), self.sigma)
        blurred = self.blurred[band]  # sums in float64 without float64 copies of the band
        self.g_sum = float(np.sum(blurred, dtype=np.float64))
        self.g_sq = float(np.einsum("ij,ij->", blurred, blurred, dtype=np.float64))
        voted = ba[rows]
        self.n_events = float(np.sum(voted, dtype=np.float64))
        voted = voted[voted != 0].astype(np.float64)  # a pixel without votes adds 1 - exp(0) = 0 to the area
        self.area = float(np.sum(1.0 - np.exp(voted / -self.lambda0)))


def perturbation_objective(cost_and_grad, base: np.ndarray, first_free: int, gauge_free: bool = False):
    """The BA's parameters: left perturbations x (3 per control pose from ``first_free`` on) of the control poses
    ``base``, R_i = exp(x_i) R_i; with ``gauge_free`` their common rotation is projected out (x_i - mean x: the first
    window, see ``_refine``). Returns (step, objective): step(x), the perturbations applied, (n, 3); objective(x) =
    (cost, gradient w.r.t. x) from ``cost_and_grad(control_R) -> (cost, (M, 3) left-perturbation gradient)``."""

    def step(x: np.ndarray) -> np.ndarray:
        delta = x.reshape(-1, 3)
        return delta - delta.mean(axis=0) if gauge_free else delta

    def objective(x: np.ndarray):
        delta = step(x)
        ctrl = base.copy()
        ctrl[first_free:] = so3.exp(delta) @ base[first_free:]
        cost, grad = cost_and_grad(ctrl)
        # chain the left-perturbation gradient through exp: d/dx exp(x) R = Jl(x)
        g = np.einsum("nji,nj->ni", so3.left_jacobian(delta), grad[first_free:])
        if gauge_free:
            g = g - g.mean(axis=0)  # the chain through step's projection (symmetric)
        return cost, g.reshape(-1)

    return step, objective


class WindowObserver:
    """Notified by the back-end around every window; this default does nothing. Loop closure
    (pipelines/loop_closure.LoopCloser) is one: it reads the back-end and changes it only through
    ``SlidingWindowBackend.correct_poses`` and ``drop_map`` (the back-end then asks it for ``rebuilt_map``)."""

    stage: str | None = None  # the StageClock stage its calls are timed under (None: untimed)
    loops: list | None = None  # what it reports (report.json "loops"), if anything

    def before_window(self, t0: float, t1: float, final: bool = False, idle_only: bool = False) -> None:
        """The window [t0, t1] has its control poses initialised; its BA comes next. ``idle_only``: the back-end is
        behind its input (the real-time budget): work that can wait waits for idle time."""

    def settled(self, ev_t: np.ndarray, ev_b: np.ndarray, t0: float, moving: bool) -> None:
        """The events of the stride starting at t0 went into the global map: times (m,), bearings (3, m) (views of
        the back-end's buffer: copy what is kept)."""

    def after_window(self, t_now: float) -> None:
        """The window slid: the events before t_now are settled."""

    def rebuilt_map(self) -> GlobalMap:
        """The global map after ``drop_map`` (never called unless the observer dropped it)."""
        raise RuntimeError("the back-end's map was dropped by an observer that cannot rebuild it")

    def pending(self) -> bool:
        """Work in flight that ``idle_slice`` would advance."""
        return False

    def idle_slice(self) -> None:
        """Advance work in flight while the caller has nothing else to do."""

    def drain(self) -> None:
        """The stream ends: finish work in flight now."""

    def summary(self) -> dict | None:
        """The report's block on this observer (None: none)."""
        return None


@dataclass
class WindowUpdate:
    """A completed window as a worker process sends it: its report and the control poses from ``first`` on (those
    before did not change), for a mirror back-end that answers pose queries (``SlidingWindowBackend.follow``)."""

    report: WindowReport
    first: int
    tail: np.ndarray
    anchor: tuple
    window_start: float
    shape: tuple  # (degree, t0, dt) of the spline


# a BFGS cold start on a window of at least COARSE_MIN_EVENTS events climbs first on every COARSE-th of them
# (SlidingWindowBackend._maximise)
COARSE, COARSE_MIN_EVENTS = 4, 100_000


class _Relative:
    """An objective x -> (cost, gradient) divided by var0, its cost at the initialisation (x = 0): the first call's
    when that is at x = 0, else ``initial()``'s, unless ``start`` gave it first."""

    def __init__(self, fun, initial):
        self.fun, self.initial = fun, initial
        self.var0 = self.scale = None

    def start(self, var0: float) -> None:
        self.var0, self.scale = var0, (1.0 / var0 if var0 > 0 else 1.0)

    def __call__(self, x: np.ndarray):
        var, g = self.fun(x)
        if self.scale is None:
            self.start(var if not np.any(x) else self.initial())
        return var * self.scale, g * self.scale


class SlidingWindowBackend:
    """Online sliding-window BA over a spline trajectory and a panoramic map (see module docstring)."""

    def __init__(self, config: BackendConfig, t_start: float, r_start: np.ndarray | None = None,
                 events: _Buffer | None = None):
        """``config`` must be resolved for the camera (``sensor_defaults.resolve_backend``): no derived 0s. ``events``:
        an empty event buffer prepared for the stream's rate (``event_buffer``), else a new one."""
        if config.pano_height <= 0 or config.backend_max_window_events == 0 or config.backend_min_ev_rate <= 0:
            raise ValueError("the back-end needs a config resolved for the camera (sensor_defaults.resolve_backend)")
        self.cfg = config
        self.width, self.height = config.pano_size
        self.t_start = float(t_start)
        self.r_start = np.eye(3) if r_start is None else np.asarray(r_start, dtype=float)
        # the global map I_G; None while an observer rebuilds it (drop_map, refresh_map)
        self.map: GlobalMap | None = self.new_map()
        self.ba_width = self.map.ba_size[0]  # the BA's map width (the reach of a vote in radians)
        self.spline: SO3Spline | None = None
        self.window_start = self.t_start
        self.events = events if events is not None else event_buffer(config)
        self._settle_work = VoteWork()  # the settle's projection and vote arrays, kept between strides
        self._ba_work, self._coarse_work = VoteWork(), VoteWork()  # the BA's (and its coarse start's), between windows
        self.events_until = -np.inf  # all events with t < events_until have been pushed
        self._src_t = np.zeros(0)
        self._src_R = np.zeros((0, 3, 3))
        self._src_moves: deque[tuple[float, float]] = deque()  # (t_a, t_b): spans over which the source moved
        self._anchor: tuple[float, np.ndarray, np.ndarray] | None = None  # (t, R_src(t), R_spline(t))
        self.windows: list[WindowReport] = []
        self.events_settled = 0
        self.events_optimized = 0  # event-window pairs that went through BA
        self._last_correction: float | None = None  # |x| of the last window's BA solution
        # the accepted corrections of the last windows (rad), the source's typical error (policy.departure_bound)
        self._corrections: deque[float] = deque(maxlen=policy.RECENT_WINDOWS)
        self._inv_hessian = None  # BFGS: (first free control pose, inverse Hessian) of the last window
        self.fitted_from: int | None = None  # the first control pose a fit changed since the last update (updates)
        self._fitted_after: tuple | None = None  # the anchor the last _initialize_until continued from
        self.corrections = 0  # observers' corrections of the control poses (correct_poses)
        self._corrections_sent = 0  # corrections the last update covered (updates)
        self.observer = WindowObserver()
        self.clock = StageClock()  # per-stage CPU and wall seconds (fit, ba, settle, and the observer's)

    def new_map(self) -> GlobalMap:
        """An empty global map of this back-end's size, blur, BA-map downsampling (a config that sets the map's size
        and the window cap but leaves the factor derived: the BA reads the map itself) and pixel freezing."""
        cfg = self.cfg
        return GlobalMap(self.width, self.height, cfg.backend_blur_sigma, cfg.lambda0,
                         cfg.max_update_time if cfg.freeze_pixels else None, max(1, cfg.backend_map_downsample))

    def attach(self, observer: WindowObserver) -> None:
        """Notify ``observer`` around every window from now on (one observer)."""
        self.observer = observer

    # ---- what observers may change ----------------------------------------------------------------------------
    def correct_poses(self, correct) -> None:
        """An observer's correction of the control poses (loop closure): ``correct(spline)`` edits them in place;
        the anchor follows, and a rejected BA's refit no longer restarts from the uncorrected anchor."""
        correct(self.spline)
        self._anchor_at(self._anchor[0])
        self._fitted_after = None
        self.corrections += 1

    def drop_map(self) -> None:
        """An observer replaces the global map: strides settle no votes until ``refresh_map`` asks it for the new one
        (several replacements between two reads cost one rebuild)."""
        self.map = None

    def refresh_map(self) -> GlobalMap:
        """The global map, rebuilt by the observer first if it dropped it (timed as the observer's stage)."""
        if self.map is None:
            with self.clock(self.observer.stage):
                self.map = self.observer.rebuilt_map()
        return self.map

    # ---- input streams -------------------------------------------------------------------------------------------
    def push_events(self, t: np.ndarray, bearings: np.ndarray, complete_until: float | None = None) -> None:
        """Append events (time-sorted, already downsampled by backend_event_sample_rate) with their bearings.

        ``complete_until``: every event before this time has now been pushed (the end of the chunk read).
        """
        self.events.push(np.asarray(t, dtype=float), np.asarray(bearings, dtype=np.float32))
        if complete_until is not None:
            self.events_until = max(self.events_until, float(complete_until))
        elif len(t):
            self.events_until = max(self.events_until, float(t[-1]))

    def push_written(self, n: int, write: Callable[[np.ndarray, np.ndarray, int], None],
                     complete_until: float) -> None:
        """Append ``n`` events (as ``push_events``) that ``write(times, bearings, row)`` puts in place: rows
        row..row + n - 1 of the buffer's float64 time array and columns row..row + n - 1 of its (3, m) float32 bearing
        array (no intermediate copy)."""
        if n:
            times, bearings, row = self.events.reserve(n)
            write(times, bearings, row)
            self.events.commit(n)
        self.events_until = max(self.events_until, float(complete_until))

    def push_source_poses(self, times: np.ndarray, rotations: np.ndarray, moving=None) -> None:
        """Append samples of the initializing trajectory (only relative rotations are used). ``moving`` (one bool
        per sample): whether the source measured a motion there (the front-end: a packet that is not still); None
        (a given trajectory, IMU): moving throughout, every window gets its BA."""
        times = np.asarray(times, dtype=float).reshape(-1)
        rotations = np.asarray(rotations, dtype=float).reshape(-1, 3, 3)
        keep = times > (self._src_t[-1] if len(self._src_t) else -np.inf)
        times, rotations = times[keep], rotations[keep]
        moved = np.ones(len(times), bool) if moving is None else np.asarray(moving, dtype=bool).reshape(-1)[keep]
        prev = np.concatenate([self._src_t[-1:] if len(self._src_t) else times[:1], times[:-1]])
        # a measured motion spans the intervals on both sides of its sample
        self._src_moves.extend(zip(prev[moved].tolist(), (2 * times - prev)[moved].tolist()))
        self._src_t = np.concatenate([self._src_t, times])
        self._src_R = np.concatenate([self._src_R, rotations])

    # ---- stepping --------------------------------------------------------------------------------------------------
    @property
    def window_end(self) -> float:
        return self.window_start + self.cfg.backend_time_window_size

    def ready(self) -> bool:
        """A full window of events and source poses is available."""
        src_end = self._src_t[-1] if len(self._src_t) else -np.inf
        return src_end >= self.window_end - _TIME_EPS and self.events_until >= self.window_end

    def step(self, budget: WindowBudget = FULL_BUDGET, final: bool = False) -> WindowReport:
        """One window (paper Sec. IV): slide the window, initialise the control poses it adds from the source,
        maximise the panoramic IWE's variance over its free control poses, and settle its first stride into the
        global map. ``budget``: what the real-time controller grants the BA; ``final`` settles every event left."""
        tic, stride = time.perf_counter(), self.cfg.backend_sliding_window_stride
        window = self._slide(final)  # 1. slide the window
        ev_t, ev_b = self.events.range(window.t0, window.t1, include_end=True)
        report = WindowReport(window.t0, window.t1, len(ev_t), optimized=False, alpha=0.0)
        moving_from = policy.motion_start(self._src_moves, self._src_t, window) \
            if self.cfg.backend_skip_still_windows else window.t0
        report.no_ba = policy.why_no_ba(len(ev_t), window, moving_from, budget, len(self.windows), self.cfg)
        if policy.fit_due(len(ev_t), window, self.fitted_until, stride):  # 2. initialise the new control poses
            with self.clock("fit"):
                self._initialize_until(window.t1, refit_past=report.no_ba is not None)
        with self.clock(self.observer.stage):
            self.observer.before_window(window.t0, window.t1, window.final, budget.loop_idle_only)
        if report.no_ba is None:  # 3. maximise the contrast over the window's free control poses
            self._adjust(ev_t, ev_b, window, report, moving_from, budget)
        with self.clock("settle"):  # 4. update the map with the first stride's events
            self._settle(window.t0, window.settle_end(stride), moving=report.optimized)
        self.window_start = window.t0 + stride
        with self.clock(self.observer.stage):
            self.observer.after_window(self.window_start)
        self._drop_source_before_anchor()
        report.seconds, report.done_at = time.perf_counter() - tic, time.monotonic()
        self.windows.append(report)
        return report

    def finish(self, budget: WindowBudget = FULL_BUDGET) -> None:
        """Process the windows left once both streams have ended (the observer's work in flight first)."""
        self.observer.drain()
        end = max(self.events.t[-1] if len(self.events.t) else self.window_start,
                  self._src_t[-1] if len(self._src_t) else self.window_start)
        while self.window_end < end - _TIME_EPS:
            self.step(budget)
        if self.window_start <= end:
            self.step(budget, final=True)
        self.refresh_map()  # the output map, rebuilt after the observer's last correction

    def _slide(self, final: bool) -> Window:
        """The window at window_start; the final one ends at the stream's end (policy.partial_window_end)."""
        t0, t1 = self.window_start, self.window_end
        if final:
            t1 = policy.partial_window_end(t0, t1, self.events.t[-1] if len(self.events.t) else t0,
                                           self._src_t[-1] if len(self._src_t) else t0)
        return Window(t0, t1, final)

    def _adjust(self, ev_t, ev_b, window: Window, report: WindowReport, moving_from: float, budget) -> None:
        """The window's BA: maximise the contrast over its free control poses, fix the gauge after the first one,
        and refit a rejected window as one without a BA (else runs of rejected windows overshoot in turn)."""
        self.refresh_map()  # the map the BA reads, after an observer's correction
        ba0 = time.perf_counter()
        with self.clock("ba"):
            self._refine(ev_t, ev_b, window.t0, report, moving_from, budget)
            if window.t0 <= self.t_start + _TIME_EPS:
                self._fix_gauge()
        if report.rejected and self._fitted_after is not None:
            with self.clock("fit"):
                self._anchor = self._fitted_after
                self._initialize_until(window.t1, refit_past=True)
        report.ba_seconds = time.perf_counter() - ba0

    # ---- results ---------------------------------------------------------------------------------------------------
    def trajectory(self, rate: float) -> Trajectory:
        """The refined continuous trajectory sampled at ``rate`` Hz over its valid range."""
        if self.spline is None:
            return Trajectory(np.array([self.t_start]), self.r_start[None])
        start, end = self.spline.valid_time_range()
        last = self.events_until if np.isfinite(self.events_until) else end
        return self.spline.to_trajectory(rate, max(start, self.t_start), min(end, last))

    def pose_at(self, times) -> np.ndarray:
        """Best estimate of R(t) now, (M, 3, 3): the spline up to its last initialized pose (refined where windows
        are done), beyond it the source poses re-anchored to the spline (extrapolated past the last sample)."""
        times = np.atleast_1d(np.asarray(times, dtype=float))
        out = np.broadcast_to(self.r_start, (len(times), 3, 3)).copy()
        if len(self._src_t) == 0:
            return out
        t_a, r_src_a, r_spl_a = self._anchor or (self.t_start, self._source_at(self.t_start), self.r_start)
        inside = times <= t_a + _TIME_EPS if self.spline is not None else np.zeros(len(times), bool)
        if inside.any():
            start, end = self.spline.valid_time_range()
            out[inside] = self.spline.evaluate(np.clip(times[inside], start, end))
        for i in np.flatnonzero(~inside):
            t = times[i]
            out[i] = self._extrapolate(t) if t > self._src_t[-1] else r_spl_a @ r_src_a.T @ self._source_at(t)
        return out

    @property
    def fitted_until(self) -> float | None:
        """The spline's control poses are fitted (to the source, then refined) up to this time (the anchor)."""
        return None if self._anchor is None else self._anchor[0]

    @property
    def refined_until(self) -> float:
        """Windows are done (events settled into the map) up to this time."""
        return self.window_start if self.windows else self.t_start

    def updates(self, since: int) -> list[WindowUpdate]:
        """The windows completed from ``since`` on as updates for a mirror (``follow``): the control poses from one
        before each window's first free one (those a fit changed, if earlier), all of them after a correction."""
        spline, out = self.spline, []
        for report in self.windows[since:]:
            fitted = self.fitted_from if self.fitted_from is not None else len(spline.control_R)
            first = 0 if self.corrections > self._corrections_sent else \
                max(0, min(int(np.floor((report.t_start - spline.t0) / spline.dt)) - 1, fitted))
            self._corrections_sent, self.fitted_from = self.corrections, None
            out.append(WindowUpdate(report, first, spline.control_R[first:].copy(), self._anchor, self.window_start,
                                    (spline.degree, spline.t0, spline.dt)))
        return out

    def follow(self, update: WindowUpdate) -> None:
        """Mirror a window computed elsewhere (a worker process's back-end): its control poses, anchor and report.
        A mirror only answers ``pose_at`` and ``refined_until``; it never refines."""
        if self.spline is None:
            self.spline = SO3Spline(*update.shape, update.tail)
        else:
            self.spline.control_R = np.concatenate([self.spline.control_R[:update.first], update.tail])
        self._anchor, self.window_start = update.anchor, update.window_start
        self._drop_source_before_anchor()
        self.windows.append(update.report)

    # ---- internals -------------------------------------------------------------------------------------------------
    def _source_segment(self, t_from: float, t_to: float) -> tuple[np.ndarray, np.ndarray]:
        """Source poses in (t_from, t_to] plus the first one beyond t_to + TIME_EPS, re-anchored to the spline at
        the anchor. A sample that only coincides with t_to (to rounding) does not count as beyond: it would leave
        the control poses of the window's end unconstrained."""
        i0 = int(np.searchsorted(self._src_t, t_from, side="right"))
        i1 = min(int(np.searchsorted(self._src_t, t_to + _TIME_EPS, side="right")) + 1, len(self._src_t))
        times, rots = self._src_t[i0:i1], self._src_R[i0:i1]
        t_a, r_src_a, r_spl_a = self._anchor
        return times, r_spl_a @ r_src_a.T @ rots

    def _drop_source_before_anchor(self) -> None:
        """Forget source poses before the anchor's interval: later windows, pose_at and the extrapolation only read
        the source from the anchor on, so memory and the per-packet append stay bounded on long streams."""
        if self._anchor is None:
            return
        i = int(np.searchsorted(self._src_t, self._anchor[0], side="left")) - 1
        i = min(i, len(self._src_t) - 2)
        if i > 0:
            self._src_t, self._src_R = self._src_t[i:], self._src_R[i:]

    def _source_at(self, t: float) -> np.ndarray:
        return Trajectory(self._src_t, self._src_R).at(t)[0] if len(self._src_t) > 1 else self._src_R[0]

    def _initialize_first(self, t_end: float) -> None:
        """The first window's control poses: fitted to the source from r_start at t_start."""
        cfg = self.cfg
        r_src0 = self._source_at(self.t_start)
        self._anchor = (self.t_start, r_src0, self.r_start)
        times, rots = self._source_segment(self.t_start, t_end)
        times = np.concatenate([[self.t_start], times])
        rots = np.concatenate([self.r_start[None], rots])
        if len(times) < 2:
            times, rots = np.array([self.t_start, t_end]), np.stack([self.r_start, self.r_start])
        elif times[-1] < t_end:  # the source ends before the events do (a stream shorter than one window)
            times, rots = np.append(times, t_end), np.concatenate([rots, self._extrapolate(t_end)[None]])
        lead = (cfg.spline_degree - 1) // 2
        self.spline = SO3Spline(cfg.spline_degree, self.t_start - lead * cfg.dt_knots, cfg.dt_knots,
                                np.broadcast_to(self.r_start, (cfg.spline_degree + 1, 3, 3)).copy())
        self.spline.fit_new_segment(times, rots, first_free=0, refine_iters=1)
        self._anchor_at(float(times[-1]))
        self.fitted_from = 0
        self._fitted_after = None

    def _initialize_until(self, t_end: float, refit_past: bool = False) -> None:
        """Fit control poses for (anchor, t_end] to the re-anchored source (lift-solve-retract; paper Sec. III-C2,
        Initialization: each new segment starts from the last optimised pose).

        ``refit_past`` (a window that gets no BA): the control poses that shape R(t) just after the anchor but were
        fixed before it are refitted too, to the spline's own samples over the preceding knot intervals plus the new
        ones. The new poses alone would continue whatever slope the last BA left at the window's end, and over
        windows without a BA to damp it cubic poses overshoot in turn, window by window. A window with a BA keeps
        the plain fit (its BA refines those poses anyway)."""
        if self.spline is None:
            self._initialize_first(t_end)
            return
        cfg = self.cfg
        t_a = self._anchor[0]
        if t_end <= t_a + _TIME_EPS and self.spline.valid_time_range()[1] >= t_end - _TIME_EPS:
            self._fitted_after = None
            return
        self._fitted_after = self._anchor  # the anchor this fit continued from (a rejected BA refits from there)
        times, rots = self._source_segment(t_a, t_end)
        # knots after the anchor were only extrapolated so far: refit them together with the new ones
        first_free = int(np.searchsorted(self.spline.knot_times(), t_a + _TIME_EPS, side="right"))
        if len(times) == 0:  # no new source samples: hold the last pose
            times, rots = np.array([max(t_end, t_a + 1e-6)]), self._anchor[2][None]
        elif times[-1] < t_end:  # the source ends before the events do: extrapolate its last velocity
            times, rots = np.append(times, t_end), np.concatenate([rots, self._extrapolate(t_end)[None]])
        # include the anchor itself so the new segment starts where the optimized trajectory is
        times = np.concatenate([[t_a], times])
        rots = np.concatenate([self._anchor[2][None], rots])
        start, end = self.spline.valid_time_range()
        shaping = int(self.spline.support(min(t_a, end))[0][0])  # first pose that shapes R(t) at the anchor
        if refit_past and 1 <= shaping < first_free:
            # samples every half knot interval over the knot intervals those poses shape before the anchor
            past = t_a - 0.5 * cfg.dt_knots * np.arange(2 * cfg.spline_degree, 0, -1)
            past = past[past >= start]
            times = np.concatenate([past, times])
            rots = np.concatenate([self.spline.evaluate(past), rots])
            first_free = shaping
        self.spline.fit_new_segment(times, rots, first_free=first_free, refine_iters=1)
        self._anchor_at(float(times[-1]))
        self.fitted_from = first_free if self.fitted_from is None else min(self.fitted_from, first_free)

    def _fix_gauge(self) -> None:
        """After the first window's BA: R(t_start) = r_start exactly (policy.gauge_fix)."""
        turn = policy.gauge_fix(self.spline, self.t_start, self.r_start)
        if turn is not None:
            self.spline.control_R[:] = turn @ self.spline.control_R
            self._anchor_at(self._anchor[0])

    def _extrapolate(self, t: float) -> np.ndarray:
        """Re-anchored source pose at t beyond its last sample, at the last sampled angular velocity."""
        t_a, r_src_a, r_spl_a = self._anchor or (self.t_start, self._source_at(self.t_start), self.r_start)
        r_last = self._src_R[-1]
        if len(self._src_t) > 1:
            dt = self._src_t[-1] - self._src_t[-2]
            w = so3.log(self._src_R[-2].T @ r_last) / dt
            r_last = r_last @ so3.exp(w * (t - self._src_t[-1]))
        return r_spl_a @ r_src_a.T @ r_last

    def _anchor_at(self, t: float) -> None:
        self._anchor = (t, self._source_at(t), self.spline.evaluate(t)[0])

    def _refine(self, ev_t, ev_b, t0, report: WindowReport, moving_from: float | None = None,
                budget: WindowBudget = FULL_BUDGET) -> None:
        """Maximise Var(B(I_L) + alpha B(I_G)) (Eq. 18) over the control poses from the first free one, on left
        increments, and apply the optimum unless it is a false maximum: a correction beyond backend_max_correction
        (policy.false_maximum), or one beyond the check's bound (policy.departs) unless a local refit confirms it or
        replaces it (``_recheck``)."""
        cfg, spline = self.cfg, self.spline
        sample = policy.even_sample_index(len(ev_t), cfg.backend_max_window_events if budget.ba_cap is None
                                          else budget.ba_cap)
        if sample is not None:  # the sampled bearings (3, k); of the times only the batches' first and last are read
            taken = self._ba_work.take("sample", (3, len(sample)), np.float32)
            for row, out in zip(ev_b, taken):  # row by row: a take along axis 1 of the buffer's view is ~5x slower
                np.take(row, sample, out=out, mode="clip")  # (valid indices: "clip" writes out unbuffered)
            ev_b = taken
        report.events_used = ev_b.shape[1]
        first_free = policy.first_free_pose(spline.knot_times(), t0, moving_from, cfg)
        s, u = spline.support(batch_mid_times(ev_t, cfg.event_batch_size, index=sample))
        # alpha from the event densities of the initial local map and the global map (Eq. 16-17): PanoIWE takes
        # rho(I_L) from its first evaluation, the optimiser's start at the initialization
        rho_g = self.map.density
        problem = PanoIWE(ev_b, s, u, cfg.spline_degree, *self.map.ba_size, sigma=cfg.backend_blur_sigma,
                          alpha=0.0, batch_size=cfg.event_batch_size, coordinate_rows=True,
                          global_blurred=self.map.blurred, global_sums=(self.map.g_sum, self.map.g_sq),
                          alpha_from_density=(rho_g, self.map.lambda0) if rho_g > 0 else None, work=self._ba_work)
        base = spline.control_R.copy()
        n_free = len(base) - first_free
        if n_free <= 0:
            return
        gauge_free = policy.gauge_free(t0, self.t_start, first_free)
        step, perturbed = perturbation_objective(problem.cost_and_grad, base, first_free, gauge_free)

        def coarse(alpha: float):  # the same objective over every COARSE-th event (a cold start's first climb)
            rows = np.arange(0, ev_b.shape[1], COARSE)
            s_k, u_k = spline.support(batch_mid_times(ev_t, cfg.event_batch_size,
                                                      index=rows if sample is None else sample[rows]))
            # I_L holds 1/COARSE of the votes: alpha / COARSE keeps the balance of I_L and I_G (Eq. 18)
            few = PanoIWE(ev_b[:, rows], s_k, u_k, cfg.spline_degree, *self.map.ba_size, sigma=cfg.backend_blur_sigma,
                          alpha=alpha / COARSE, batch_size=cfg.event_batch_size, global_blurred=self.map.blurred,
                          coordinate_rows=True,
                          global_sums=(self.map.g_sum, self.map.g_sq), work=self._coarse_work)
            return perturbation_objective(few.cost_and_grad, base, first_free, gauge_free)[1]

        result, var0, scale = self._maximise(problem, perturbed, base, first_free, n_free, budget,
                                             coarse=coarse if ev_b.shape[1] >= COARSE_MIN_EVENTS else None)
        report.alpha = problem.alpha  # set by the first evaluation
        # the correction: how far the optimum moves the trajectory where the window's events are (not how far it
        # moves control poses, which the events may barely reach)
        s_c, u_c = policy.correction_samples(s, u)

        def trajectory_at(res) -> np.ndarray:  # the trajectory at the samples with the optimum res applied
            spline.control_R[first_free:] = so3.exp(step(res.x)) @ base[first_free:]
            return spline.evaluate_at(s_c, u_c)

        def refit(step_bound: float):  # a local refit from the initialisation (its optimum)
            return self._maximise(problem, perturbed, base, first_free, n_free, budget, step_bound=step_bound)[0]

        before = spline.evaluate_at(s_c, u_c)
        after = trajectory_at(result)
        report.max_correction = _largest_angle(before, after)
        report.false_maximum = policy.false_maximum(report.max_correction, cfg)
        evaluations = result.evaluations
        if report.false_maximum is None:
            result, evaluations = self._recheck(result, before, after, trajectory_at, refit, report)
        report.evaluations = evaluations
        if report.false_maximum is not None and not report.refitted:
            spline.control_R[:] = base  # the window keeps its initialization
            report.rejected = True
            self._inv_hessian = None  # the curvature of a false maximum
            return
        self._last_correction = float(np.linalg.norm(result.x))
        self._corrections.append(report.max_correction)
        report.variance_before, report.variance_after = var0, result.fun / scale
        report.optimized, report.iterations = True, result.iterations
        report.cut_short = result.message == "time budget reached"
        self.events_optimized += report.events_used
        self._anchor_at(self._anchor[0])

    def _recheck(self, result, before, after, trajectory_at, refit, report: WindowReport):
        """The check of an optimum (``after``: the trajectory at the window's samples with it; ``before``: at the
        initialisation; ``trajectory_at(optimum)`` applies one and samples it there): when its correction exceeds the
        check's bound (policy.departs; the bound follows the recent windows' corrections), a local refit from the
        initialisation (``refit(step)``: no carried inverse Hessian, steps of at most the reach of a vote) decides
        (policy.refit_outcome): the first optimum confirmed, replaced by the refit's, or neither (report.false_maximum
        set and report.refitted False: the caller keeps the initialisation). Leaves the spline at the kept optimum;
        returns (it, the evaluations of both)."""
        bound = policy.departure_bound(self.ba_width, self.cfg.backend_blur_sigma, self._corrections)
        suspect = policy.departs(report.max_correction, bound)
        if suspect is None:
            return result, result.evaluations
        carried = self._inv_hessian
        local = refit(policy.departure_bound(self.ba_width, self.cfg.backend_blur_sigma))  # steps within a vote's reach
        refitted = trajectory_at(local)
        outcome = policy.refit_outcome(_largest_angle(before, refitted), _largest_angle(after, refitted), bound)
        evaluations = result.evaluations + local.evaluations
        if outcome == policy.CONFIRMED:
            report.confirmed, self._inv_hessian = True, carried
            trajectory_at(result)
            return result, evaluations
        report.false_maximum, report.refitted = suspect, outcome == policy.REFITTED
        if report.refitted:
            report.max_correction = _largest_angle(before, refitted)
        return local, evaluations

    def _maximise(self, problem, perturbed, base, first_free: int, n_free: int, budget: WindowBudget,
                  step_bound: float | None = None, coarse: Callable | None = None):
        """Run the configured optimiser (BFGS warm-started from the last window's inverse Hessian, or Fletcher-Reeves
        CG) on the relative variance: the cost divided by var0, its value at the initialization (x = 0), so the
        tolerances are scale-free. ``step_bound`` (a refit): start afresh, without the carried inverse Hessian, with
        steps of at most this length (rad; CG: its first step), so that the optimiser climbs to the maximum nearest
        to the initialisation. ``coarse(alpha)``: the objective over a subsample (``_refine``); a BFGS cold start
        (no inverse Hessian to carry: the first window, or after a rejected one) climbs on it first, then continues
        on all events from its optimum with the inverse Hessian it learnt, so the ~3 x (free poses) updates a cold
        start needs cost a fraction of an evaluation each. Returns (result, var0, 1 / var0); the result's
        evaluations include the coarse ones."""
        cfg = self.cfg
        objective = _Relative(perturbed, lambda: problem.cost(base))
        deadline = None if budget.ba_budget is None else time.monotonic() + budget.ba_budget
        init_step, max_step = self._init_step(), cfg.backend_bfgs_max_step
        if step_bound is not None:
            init_step, max_step = step_bound, min(step_bound, max_step)
        if cfg.backend_optimizer == "bfgs":
            warm = self._carried_inv_hessian(first_free, n_free) if step_bound is None else None
            x0, climbed = np.zeros(3 * n_free), None

            def run(fun, x, inv_hessian):
                return bfgs(fun, x, maximize=True, inv_hessian=inv_hessian, init_step=init_step,
                            max_iter=cfg.backend_cg_max_iters, grad_tol=cfg.backend_cg_grad_tol,
                            rel_cost_tol=cfg.backend_cg_rel_cost_tol, max_step=max_step,
                            max_line_evals=cfg.backend_cg_max_line_evals, deadline=deadline,
                            last_step_unevaluated=cfg.backend_bfgs_last_step_unevaluated)

            if warm is None and step_bound is None and coarse is not None:
                objective.start(problem.cost(base))  # the initialisation's variance (and alpha: the first evaluation)
                climbed, warm = run(_Relative(coarse(problem.alpha), None), x0, None)
                x0 = climbed.x
            result, h = run(objective, x0, warm)
            if climbed is not None:
                result = dataclasses.replace(result, iterations=result.iterations + climbed.iterations,
                                             evaluations=result.evaluations + climbed.evaluations)
            self._inv_hessian = None if h is None else (first_free, h)
        else:
            result = fletcher_reeves(
                objective, np.zeros(3 * n_free), maximize=True, init_step=init_step,
                line_search_tol=cfg.backend_cg_line_search_tol, max_iter=cfg.backend_cg_max_iters,
                grad_tol=cfg.backend_cg_grad_tol, rel_cost_tol=cfg.backend_cg_rel_cost_tol,
                max_line_evals=cfg.backend_cg_max_line_evals, step_guess=cfg.backend_cg_step_guess,
            )
        return result, objective.var0, objective.scale

    def _carried_inv_hessian(self, first_free: int, n_free: int) -> np.ndarray | None:
        """The last window's BFGS inverse Hessian re-indexed to this window's free control poses: the poses both
        windows optimise keep their blocks (windows overlap, the cost changes little there), poses new to this
        window start uncoupled with the mean diagonal. When no pose is shared (windows without a BA in between) the
        last one is the template pose by pose from the first free one: windows of one length and knot spacing have
        similar curvature, and a cold start costs many more evaluations. None before any BA (a cold start)."""
        if self._inv_hessian is None:
            return None
        prev_first, h_prev = self._inv_hessian
        offset, n_prev = first_free - prev_first, len(h_prev) // 3
        if offset < 0:
            return None
        if offset >= n_prev:
            offset = 0
        keep = min(n_prev - offset, n_free)
        h = np.diag(np.full(3 * n_free, float(np.mean(np.diag(h_prev)))))
        h[:3 * keep, :3 * keep] = h_prev[3 * offset:3 * (offset + keep), 3 * offset:3 * (offset + keep)]
        return h

    def _init_step(self) -> float:
        """First trial step: the size of the previous window's correction (windows overlap, so corrections are of
        similar size), capped by backend_cg_init_step; a first step far larger than the optimum's distance costs
        many line-search bisections."""
        cap = self.cfg.backend_cg_init_step
        if self._last_correction is None:
            return cap
        return float(np.clip(2.0 * self._last_correction, 1e-2 * cap, cap))

    def _settle(self, t0: float, t1: float, moving: bool) -> None:
        """Vote the events of [t0, t1) into the global map with the refined poses (none while an observer rebuilds
        the map: it holds them); tell the observer; drop them from the buffer. ``moving``: the window's BA ran (the
        map's pixel freezing counts observation time only then)."""
        cfg = self.cfg
        ev_t, ev_b = self.events.range(t0, t1)
        if len(ev_t):
            start, end = self.spline.valid_time_range()
            mids = np.clip(batch_mid_times(ev_t, cfg.event_batch_size), start, end)
            if self.map is not None:
                # the BA's projection and vote (PanoIWE: the spline evaluated per batch in the kernel); its window
                # holds the votes plus the radius of I_G's blur, the region B(I_G) changes on. In one part whatever
                # the thread count: the projection and the vote then run on one thread (a part's loop of PART_TASK
                # iterations is one Taichi task), which costs less CPU time than two (no second thread to wake, join
                # and wait for; the settle, unlike the BA, holds a window for a few ms only), and no copy of the
                # window per part
                s, u = self.spline.support(mids)
                local = PanoIWE(ev_b, s, u, cfg.spline_degree, self.width, self.height, sigma=self.map.sigma,
                                alpha=0.0, batch_size=cfg.event_batch_size, parts=1, coordinate_rows=True,
                                work=self._settle_work).votes(self.spline.control_R)
                if local is not None:
                    self.map.add_votes(*local, t0, moving=moving)
            self.events_settled += len(ev_t)
            self.observer.settled(ev_t, ev_b, t0, moving)
        self.events.drop_before(t1)
