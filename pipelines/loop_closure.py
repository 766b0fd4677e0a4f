"""Loop closure on revisits for the sliding-window back-end (beyond the paper, Sec. VI names it as missing).

Without it, drift builds up over a 360-degree pan until the camera sees the first turn's map again; the global map
then pulls the new windows back, so the trajectory carries the drift and a jump. ``LoopCloser`` observes a
``SlidingWindowBackend`` (``backend.attach``: the back-end notifies it around every window) and changes it only
through ``correct_poses`` and ``drop_map``:

1. store: keeps a subsample of the settled events (at most ``loop_stored_event_rate`` per second, each stride 1 of
   k with weight k; all strides thinned by 2 when ``loop_max_stored_events`` is exceeded: bounded memory), and,
   delayed by ``loop_recent_time``, marks them in a coarse map of the time each region was last observed (the cells
   of 1 in 4 events) and, once a verification reads it, votes them into an *old map* (a run without a revisit
   never casts those votes);
2. detection, before every window's BA: the recent events (the last ``loop_recent_time`` seconds of settled events
   plus the window's, at their initialized poses: the BA has not pulled them to the old map yet) are a revisit
   candidate when at least ``loop_min_overlap`` of them fall on *old* regions: observed, and last observed at least
   ``loop_min_age`` s ago or, at least ``loop_recent_time`` s ago, before the camera turned ``loop_min_travel`` (the
   rotation travelled along the settled trajectory: a fast pan comes back to its start sooner than any fixed age).
   Regions without texture give no events, so they are never observed. Checks come at most once per
   ``loop_recent_time``; while a revisit goes on without a correction to apply the interval doubles up to
   ``loop_min_age`` (not after a registration that ran off beyond ``loop_max_correction``: the overlap grows as a
   revisit goes on); after an applied loop the next check waits until the drift rate that loop measured has moved
   the map by ``loop_check_drift_px``, within the same bounds; at the stream's last window a check not due yet runs
   when the last verification was ``loop_recent_time`` or more before it (no later check could close the drift);
3. verification: one rotation C (left, world frame) registers the recent events against the old map of those
   regions alone, coarse to fine, with the back-end's machinery (``PanoIWE``: Var(B(I_recent) + alpha B(I_old)),
   BFGS from the last verification's inverse Hessian). The candidate is accepted when the registered maps correlate
   (normalized cross-correlation over the old regions >= ``loop_min_confidence``), the optimum is unique (that
   correlation over its best value 4 and 8 map pixels away >= ``loop_min_peak_ratio``) and |C| <=
   ``loop_max_correction``;
4. correction (when |C| >= ``loop_min_correction_px`` map pixels and the registration raised the correlation by at
   least ``loop_min_gain``: the data support it): C is spread over the control poses between the old visit (the
   middle of the old regions' last visit, or the last applied loop: each later revisit closes only the drift since)
   and the recent events by the chain pose graph ``so3.spread_correction`` (weights: rotation travelled between
   control poses, as drift grows with motion) up to the median time of the recent events on the old regions; later
   poses get all of C. The global map, the old map and the age map are then rebuilt from the stored subsamples
   along the corrected spline, so later windows align to one consistent map (the rebuilt old map plus the recent
   strides' votes, blurred once; stride by stride with pixel freezing). The global map is rebuilt when the back-end
   next needs it (``SlidingWindowBackend.refresh_map`` asks ``rebuilt_map``: before the next BA, for the output):
   while the BA is skipped (real-time level 4) several loops cost one rebuild and the strides settled meanwhile are
   not voted into a map about to be replaced. The old map and the age map restart from the checkpoint the last
   rebuild left when the correction left its strides' poses unchanged, so a rebuild votes the strides aged since,
   not every stride since the start (bitwise the same maps). At most once per turn (a full turn of rotation
   travelled, and most of the map's columns observed again since the last one) an accepted revisit is applied
   whatever its size, with a joint refinement of the poses since the old visit (``_joint_refine``,
   ``joint_refinement.refine_jointly``: a BA of all stored events) before the rebuild: the window BA's pull to the
   map makes later visits copy the first one's errors, the joint BA averages the visits; then the start of the
   trajectory is registered against the map of the later events (``joint_refinement.refine_start``: the first
   windows' error would stay in every later pose aligned at the start);
5. real time (``slice_seconds``, set by ``ti-cmax slam --realtime``): the verification and the rebuild after it run
   (with the joint refinement) in slices (a helper thread run as a coroutine, strictly alternating with the back-end: one cost evaluation, map
   step or stored stride per slice) for at most ``slice_seconds`` before each window and in the back-end worker's
   idle time; the result is applied before the window after the verification ends (to the poses then), with the age
   map as detected; the old maps serve meanwhile. No new check while one is in flight. Offline (None) all runs at
   once.

Every candidate goes into ``loops`` (time, correction, confidence, accepted, applied, reason) for report.json.
"""
from __future__ import annotations

import math
import threading
import time

import numpy as np

from ti_cmax import so3
from ti_cmax.config import LoopClosureConfig
from ti_cmax.metrics import local_texture
from ti_cmax.kernels.pano import (
    PanoIWE, batch_mid_times, blur_radius, blur_region, equirect_numpy, event_density,
)

from .backend import GlobalMap, WindowObserver
from .joint_refinement import refine_jointly, refine_start
from .optim import bfgs

_CELL = 4  # map pixels per side of an age cell
_CELL_EVERY = 4  # the cells a stored stride observed: those of 1 in this many of its events
_VOTES_PER_SLICE = 8  # aged chunks voted into the old map per slice in a sliced verification
_RING = (4.0, 8.0)  # map pixels: distances of the uniqueness test's shifts from the optimum
_ITERS = 10  # BFGS iterations per pyramid level: 3 unknowns, started near the optimum by the coarser level
_STEP_TOL = 0.05  # level pixels: BFGS stops when its next step would move the map less (1/20 of the blur)
_TEXTURE = 3  # map pixels: scale of the local texture normalization of the confidence test
_JOINT_COVERAGE = 0.9  # observed columns seen again since the last joint refinement for the next one (a turn)


def _blur_rows(raw: np.ndarray, r0: int, r1: int, sigma: float) -> tuple[np.ndarray, tuple[float, float]]:
    """``blur_map(raw)`` (float32) of a map that is zero outside rows [r0, r1), filtering only those rows and the
    blur radius around them, with the (sum, sum of squares) ``PanoIWE`` takes beside it."""
    h, w = raw.shape
    out = np.zeros((h, w), np.float32)
    rows = slice(max(r0 - blur_radius(sigma), 0), min(r1 + blur_radius(sigma), h))
    blur_region(raw, out, rows, np.arange(w), sigma)
    band = out[rows].astype(np.float64)
    return out, (float(band.sum()), float(np.sum(band * band)))


def _downsample(raw: np.ndarray, rows: np.ndarray, f: int) -> np.ndarray:
    """The map summed over f x f pixel blocks (h and w multiples of f), of a map that is zero outside ``rows``
    (sorted): only the blocks holding those rows are summed (the same sums as over the whole map)."""
    h, w = raw.shape
    out = np.zeros((h // f, w // f), raw.dtype)
    if len(rows):
        a, b = int(rows[0]) // f, int(rows[-1]) // f + 1
        out[a:b] = raw[a * f:b * f].reshape(b - a, f, w // f, f).sum(axis=(1, 3))
    return out


def _cyclic_span(used: np.ndarray, margin: int) -> np.ndarray:
    """Column indices of the shortest cyclic interval holding every True column of ``used``, widened by margin on
    both sides (all columns when that covers the width)."""
    w = len(used)
    idx = np.flatnonzero(used)
    if len(idx) == 0:
        return np.arange(w)
    gaps = np.diff(np.append(idx, idx[0] + w))  # gap after each used column, cyclically
    k = int(np.argmax(gaps))  # the interval starts after the largest gap
    start, length = int(idx[(k + 1) % len(idx)]), w - int(gaps[k]) + 1
    if length + 2 * margin >= w:
        return np.arange(w)
    return (start - margin + np.arange(length + 2 * margin)) % w


class _RawMap(GlobalMap):
    """The old map: raw votes only. The registration reads nothing else, so the blurred copy, the sums and the
    event area of ``GlobalMap`` are neither kept nor updated (2 instead of 3 float32 maps, and no blur or exp per
    aged stride). Same votes as GlobalMap.add."""

    def __init__(self, width: int, height: int, raw: np.ndarray | None = None):
        self.width, self.height = width, height
        self.raw = np.zeros((height, width), np.float32) if raw is None else raw
        self._scratch = np.zeros((height, width), np.float32)  # stays zero between calls
        self._occ = (np.zeros(width, np.int32), np.zeros(height, np.int32))

    def copy(self) -> "_RawMap":
        """A copy of the raw votes sharing the scratch map (zero between calls: one for both)."""
        twin = _RawMap(self.width, self.height, raw=self.raw.copy())
        twin._scratch = self._scratch
        return twin

    def add(self, bearings, rotations, batch_size: int, weight: float = 1.0) -> None:
        taken = self._take_votes(bearings, rotations, batch_size, 0, weight)
        if taken is not None:
            _rows, _cols, sel, votes = taken
            self.raw[sel] += votes


class _Slices:
    """A function run one slice at a time in a helper thread (a coroutine): the thread runs only from ``resume()``
    to its next ``pause()`` (or its end) while the caller waits, so exactly one of the two runs at any time (the
    same computation as a direct call, in the same order; Taichi and numpy see one caller at a time)."""

    def __init__(self, fn):
        self._go, self._back = threading.Semaphore(0), threading.Semaphore(0)
        self.done, self.result, self._error = False, None, None
        self.paused_seconds = 0.0  # wall time the thread spent paused (not working)
        self._thread = threading.Thread(target=self._run, args=(fn,), daemon=True)
        self._thread.start()

    def _run(self, fn) -> None:
        self._go.acquire()
        try:
            self.result = fn()
        except BaseException as exc:  # noqa: BLE001 - raised in the caller by resume()
            self._error = exc
        self.done = True
        self._back.release()

    def in_thread(self) -> bool:
        return threading.current_thread() is self._thread

    def pause(self) -> None:
        """In the thread: hand control back to the caller until the next resume()."""
        tic = time.perf_counter()
        self._back.release()
        self._go.acquire()
        self.paused_seconds += time.perf_counter() - tic

    def resume(self) -> None:
        """Run the thread until its next pause() or its end (raising its error, if it failed)."""
        if self.done:
            return
        self._go.release()
        self._back.acquire()
        if self._error is not None:
            raise self._error


class LoopCloser(WindowObserver):
    """Loop detection, verification and correction for one ``SlidingWindowBackend`` (module docstring)."""

    stage = "loop"  # the back-end's StageClock stage of these calls

    def __init__(self, config: LoopClosureConfig, backend, slice_seconds: float | None = None):
        """``config`` must be resolved for the camera (``sensor_defaults.resolve_config``): no derived 0s.
        ``slice_seconds``: verify in slices of at most this many wall seconds per window (real time; module
        docstring, 5.); None verifies at once."""
        if config.loop_registration_events <= 0 or config.loop_min_travel == 0:
            raise ValueError("the loop closer needs a config resolved for the camera (sensor_defaults.resolve_config)")
        self.cfg, self.backend = config, backend
        freeze = backend.map.max_update_time
        self._freeze = freeze is not None  # pixel freezing: the rebuilt global map settles every stride in order
        self._new_map = backend.new_map
        w, h = backend.width, backend.height
        self.age = np.full((-(-h // _CELL), -(-w // _CELL)), -np.inf)  # last observed (delayed); -inf: never
        self.visit = np.full_like(self.age, -np.inf)  # start of the last visit (observed after a loop_min_age gap)
        self.old = _RawMap(w, h)  # raw map of the stored events older than the recent block
        self.chunks: list[tuple[np.ndarray, np.ndarray, float, float, bool]] = []  # (t, b, weight, t0, moving)
        self._n_old = 0  # chunks already aged into the age map
        self._n_voted = 0  # chunks already voted into the old map (<= _n_old: votes wait for a verification)
        self._rot_cache: dict[int, np.ndarray] = {}  # aged chunk -> its per-batch rotations, until voted
        self._stored = 0
        self._thinned = 0  # times every chunk was thinned by 2 (a checkpoint holds the chunks as they were)
        self._checkpoint = None  # (old map, age, visit) after a rebuild: the next rebuild starts there (_rebuild)
        self.checkpoints_advanced = 0  # checkpoints moved past a loop's recent block (_advance_checkpoint)
        # rotation travelled (rad, cumulative) at the ends of the settled strides, recorded as they are stored (fixed
        # then: a later loop's correction does not change which regions counted as old, so rebuilt maps are the same)
        self._travel_rec = np.zeros((2, 1024))  # rows: times, travel; the first n_travel columns are used (grown x2)
        self._travel_rec[0, 0], self._n_travel = backend.t_start, 1
        self._next_check = backend.t_start + config.loop_min_age + config.loop_recent_time  # (or by travel: _due)
        self._interval = config.loop_recent_time  # time from one verification to the next check
        self._closed_until = -np.inf  # recent block end of the last applied loop: poses before it are closed
        self._ref = -np.inf  # reference time of the last applied loop (its poses got the whole correction)
        self._drift_rate = 0.0  # rad/s: the drift the last applied loop closed, over the time it built up in
        self._joint_travel = 0.0  # rotation travelled (rad, cumulative) at the last joint refinement
        self._joint_time = -np.inf  # time of the last joint refinement
        self.joint_refinements = 0
        self.loops: list[dict] = []
        self._inv_hessian: dict[int, np.ndarray] = {}  # per pyramid level: the last registration's (verify)
        # sliced verification (the real-time replay, pipelines/realtime.py): None verifies at once (offline);
        # else a verification runs in slices (_Slices, one cost evaluation or map step each) of at most this many
        # wall seconds before each window, and in the back-end worker's idle time (idle_slice), and its result is
        # applied before the window after it ended
        self.slice_seconds = slice_seconds
        self._idle_only = False  # the current window's budget says the back-end is behind (before_window)
        self.prepare(config, slice_seconds)
        self._task: _Slices | None = None  # the verification or map rebuild in flight
        self._pending: dict | None = None  # what its conclusion needs (_conclude_task)
        self._task_spline = None  # a sliced rebuild's corrected copy of the spline (the back-end's gets it at the end)
        # the global map is rebuilt when the back-end next asks for it (rebuilt_map: the next BA, the output), not at
        # each correction
        self.map_stale = False
        self._acc = None  # (raw map, n_voted): a sliced rebuild's global map votes so far (_finish_rebuild)
        self.map_rebuilds = 0  # global maps rebuilt (rebuilt_map)
        self.seconds = self.cpu_seconds = 0.0
        self.longest_call = (0.0, 0.0)  # (wall, CPU) seconds of the longest hook call (_spent)
        self._drained = False  # a sliced run's stream has ended (drain)
        self.profile = {"store": 0.0, "age": 0.0, "verify": 0.0, "register": 0.0, "joint": 0.0, "rebuild": 0.0}  # parts of seconds

    @staticmethod
    def prepare(config: LoopClosureConfig, slice_seconds: float | None) -> None:
        """What a sliced loop closer needs before its first slice: the joint refinement's optimizer, imported now
        (its import, ~0.3 s, would hold the back-end in one piece at the first refinement). A real-time back-end calls
        this at its start-up, before the sensor clock starts; the loop closer again when made (then a no-op)."""
        if slice_seconds is not None and config.loop_joint_refinement:
            import scipy.optimize  # noqa: F401

    # ---- notifications (from the back-end) ------------------------------------------------------------------------
    def settled(self, ev_t: np.ndarray, ev_b: np.ndarray, t0: float, moving: bool) -> None:
        """Keep a subsample of one settled stride (1 of k, weight k), its bearings as (k, 3) rows."""
        tic, cpu = time.perf_counter(), time.process_time()
        n = len(ev_t)
        stride = self.backend.cfg.backend_sliding_window_stride
        self._record_travel(float(t0), float(t0) + stride)
        cap = max(int(math.ceil(self.cfg.loop_stored_event_rate * stride)), 1)
        k = max(int(math.ceil(n / cap)), 1)
        t, b = ev_t[::k].copy(), np.ascontiguousarray(ev_b[:, ::k].T)
        self.chunks.append((t, b, n / len(t), float(t0), bool(moving)))
        self._stored += len(t)
        if self._stored > self.cfg.loop_max_stored_events:
            self.chunks = [(c[0][::2], c[1][::2], c[2] * len(c[0]) / len(c[0][::2]), c[3], c[4]) for c in self.chunks]
            self._stored = sum(len(c[0]) for c in self.chunks)
            self._thinned += 1
            self._rot_cache.clear()  # the batches changed: rotations again when voted
            self._acc = None  # (a sliced rebuild's votes of the strides as they were)
        self._spent(tic, cpu)
        self.profile["store"] += time.perf_counter() - tic

    def _record_travel(self, t0: float, t1: float) -> None:
        """Add the rotation travelled over a settled stride [t0, t1] (5 steps of the spline) to the record."""
        start, end = self.backend.spline.valid_time_range()
        n, rec = self._n_travel, self._travel_rec
        t0, t1 = max(t0, rec[0, n - 1], start), min(t1, end)
        if t1 <= t0:
            return
        rot = self.backend.spline.evaluate(np.linspace(t0, t1, 6))
        if n == rec.shape[1]:
            self._travel_rec = rec = np.concatenate([rec, np.zeros_like(rec)], axis=1)
        rec[:, n] = t1, rec[1, n - 1] + float(so3.geodesic_angle(rot[:-1], rot[1:]).sum())
        self._n_travel = n + 1

    def _due(self, t1: float) -> bool:
        """A check before the window ending at t1: at the scheduled time, or before the first one (loop_min_age +
        loop_recent_time after the start) once the camera has turned loop_min_travel since the start (a region
        may be old by travel already)."""
        if t1 >= self._next_check:
            return True
        rec = self._travel_rec
        return not self.loops and self.cfg.loop_min_travel > 0 and \
            rec[1, self._n_travel - 1] >= math.radians(self.cfg.loop_min_travel) and \
            t1 >= rec[0, 0] + 2 * self.cfg.loop_recent_time

    def _last_chance(self, t1: float) -> bool:
        """At the last window a check not due yet runs when the last verification was at least loop_recent_time
        before it: no later check could close the drift built up since (a revisit still going on at the end of
        the stream is closed there, offline and in real time: drain() verifies at once)."""
        return bool(self.loops) and t1 >= self.loops[-1]["time"] + self.cfg.loop_recent_time

    def old_before(self, t_now: float) -> float:
        """Map regions last observed before this time are old at t_now: at least ``loop_min_age`` s ago, or at
        least ``loop_recent_time`` s ago and before the camera turned ``loop_min_travel`` (the last recorded
        stride end with that much rotation travelled after it; -1: the age alone)."""
        cfg = self.cfg
        before = t_now - cfg.loop_min_age
        if cfg.loop_min_travel > 0:
            times, travel = self._travel_rec[:, :self._n_travel]
            now = np.interp(t_now, times, travel)
            i = int(np.searchsorted(travel, now - math.radians(cfg.loop_min_travel), side="right")) - 1
            if i >= 0:
                before = max(before, min(float(times[i]), t_now - cfg.loop_recent_time))
        return before

    def before_window(self, t0: float, t1: float, final: bool = False, idle_only: bool = False) -> None:
        """Before the BA of window [t0, t1] (its control poses initialized): look for a revisit in the recent
        events plus the window's, and close it. The window's events are still at their initialized poses: the
        BA has not pulled them to the old map yet (that pull, spread over the windows that enter the old
        regions, is the jump at a loop, and it hides the loop's error from a later check). ``final``: the last
        window of the stream (``_last_chance``). ``idle_only`` (sliced: the back-end is behind its input): a task
        in flight gets no slice before this window, only the worker's idle time."""
        self._idle_only = idle_only and self.slice_seconds is not None
        if self._task is not None:  # a sliced verification or rebuild in flight: its slices, no new check meanwhile
            tic, cpu = time.perf_counter(), time.process_time()
            self._window_slice()
            if self._task.done:
                self._conclude_task()
            self._spent(tic, cpu)
            return
        if not (self._due(t1) or final and self._last_chance(t1)):
            return
        tic, cpu = time.perf_counter(), time.process_time()
        ev_t, ev_b = self.backend.events.range(t0, t1, include_end=True)
        cap = max(int(math.ceil(self.cfg.loop_stored_event_rate * (t1 - t0))), 1)  # as stored (settled())
        k = max(int(math.ceil(len(ev_t) / cap)), 1)
        self._check(t1, ev_t[::k], ev_b[:, ::k].T)
        self._spent(tic, cpu)

    def after_window(self, t_now: float) -> None:
        """Age the stored events older than loop_recent_time into the old map and the age map."""
        tic, cpu = time.perf_counter(), time.process_time()
        recent = self.cfg.loop_recent_time
        while self._n_old < len(self.chunks) and self.chunks[self._n_old][0][-1] < t_now - recent:
            self._advance_checkpoint()
            self._rot_cache[self._n_old] = self._age_chunk(self.chunks[self._n_old], vote=False)
            self._n_old += 1
        self.profile["age"] += time.perf_counter() - tic
        self._spent(tic, cpu)

    def _spent(self, tic: float, cpu: float) -> None:
        """Add the wall and CPU time since (tic, cpu) to the loop closer's totals (CPU time: comparable on a
        loaded machine, where wall time is not)."""
        wall, used = time.perf_counter() - tic, time.process_time() - cpu
        self.seconds += wall
        self.cpu_seconds += used
        # the longest the loop closer held the back-end in one call (a stall of the windows behind it; after a
        # sliced run's end-of-stream drain no window follows the last ones)
        if not self._drained:
            self.longest_call = (max(self.longest_call[0], wall), max(self.longest_call[1], used))

    # ---- detection and verification ----------------------------------------------------------------------------
    def _spline(self):
        """The spline the votes go along: the corrected copy in a sliced rebuild's thread, else the back-end's."""
        task = self._task
        if self._task_spline is not None and task is not None and task.in_thread():
            return self._task_spline
        return self.backend.spline

    def _rotations(self, t: np.ndarray, ctrl_left: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """(batch mid-times clipped to the spline, per-batch rotations) of events at times t."""
        spline = self._spline()
        start, end = spline.valid_time_range()
        mids = np.clip(batch_mid_times(t, self.backend.cfg.event_batch_size), start, end)
        rot = spline.evaluate(mids)
        return mids, rot if ctrl_left is None else ctrl_left @ rot

    def _cells(self, b: np.ndarray, rot: np.ndarray, every: int = 1) -> np.ndarray:
        """Flat age-cell index of each event (``every``: of 1 in this many)."""
        bs = self.backend.cfg.event_batch_size
        if every > 1:
            idx = np.arange(0, len(b), every)
            xw = np.einsum("nij,nj->ni", rot[idx // bs], b[idx].astype(np.float64))
        else:
            xw = np.einsum("nij,nj->ni", np.repeat(rot, bs, axis=0)[: len(b)], b.astype(np.float64))
        u, v = equirect_numpy(xw, self.backend.width, self.backend.height)
        ci = np.clip((v // _CELL).astype(np.int64), 0, self.age.shape[0] - 1)
        cj = (u // _CELL).astype(np.int64) % self.age.shape[1]
        return ci * self.age.shape[1] + cj

    def _age_chunk(self, chunk, maps=None, vote: bool = True) -> np.ndarray:
        """Mark a stored chunk's cells in the age and visit maps and vote it into the old map (``maps``: into
        (old, age, visit) instead of the loop closer's own; ``vote`` False: the caller votes it later, with the
        per-batch rotations returned)."""
        old, age, visit = maps if maps is not None else (self.old, self.age, self.visit)
        t, b, weight, t0, moving = chunk
        _, rot = self._rotations(t)
        if vote:
            old.add(b, rot, self.backend.cfg.event_batch_size, weight=weight)
        hit = np.zeros(age.size, bool)
        hit[self._cells(b, rot, _CELL_EVERY)] = True
        cells = np.flatnonzero(hit)  # sorted, without np.unique's sort
        new_visit = age.flat[cells] < self.old_before(float(t[0]))  # never observed, or old
        visit.flat[cells[new_visit]] = float(t[0])
        age.flat[cells] = np.maximum(age.flat[cells], float(t[-1]))
        return rot

    def _vote_aged(self, n: int) -> None:
        """Vote the aged chunks up to n into the old map. Ageing marks the age and visit maps only (detection
        reads nothing else); the votes wait for the first verification that reads the old map, so a run without
        a revisit never casts them. Along the rotations the chunks were aged with: no loop moved their poses
        since (a rebuild votes every chunk again and empties the queue), so the same votes in the same order."""
        bs = self.backend.cfg.event_batch_size
        while self._n_voted < n:
            if self._n_voted % _VOTES_PER_SLICE == 0:
                self._slice_point()
            t, b, weight, _t0, _moving = self.chunks[self._n_voted]
            rot = self._rot_cache.pop(self._n_voted, None)
            self.old.add(b, self._rotations(t)[1] if rot is None else rot, bs, weight=weight)
            self._n_voted += 1

    def _recent_events(self, ev_t, ev_b) -> tuple[np.ndarray, np.ndarray]:
        """The stored events not aged yet, then (ev_t, ev_b); thinned to loop_registration_events."""
        t = np.concatenate([c[0] for c in self.chunks[self._n_old:]] + [np.asarray(ev_t, float)])
        b = np.concatenate([c[1] for c in self.chunks[self._n_old:]] + [np.asarray(ev_b, np.float32).reshape(-1, 3)])
        k = max(int(math.ceil(len(t) / max(self.cfg.loop_registration_events, 1))), 1)
        return t[::k], b[::k]

    def _check(self, t_now: float, ev_t, ev_b) -> None:
        cfg = self.cfg
        t, b = self._recent_events(ev_t, ev_b)
        if len(t) < 2 * self.backend.cfg.event_batch_size:
            return
        old_cells = (self.age > -np.inf) & (self.age < self.old_before(t_now))
        _, rot = self._rotations(t)
        on_old = old_cells.flat[self._cells(b, rot, _CELL_EVERY)]  # the fraction: 1 in 4 of the events tells it
        overlap = float(np.mean(on_old))
        if overlap < cfg.loop_min_overlap:
            self._interval = cfg.loop_recent_time
            return
        entry = {"time": float(t_now), "overlap": overlap}
        if self.slice_seconds is not None:  # in slices: before this window and the next ones, and when idle
            n_aged = self._n_old
            self._task = _Slices(lambda: self.verify(t, b, old_cells, n_aged))
            # the age and visit maps as detected: strides aged while the verification runs (the recent events
            # among them) must not make the old visit look recent (_apply)
            self._pending = {"kind": "verify", "entry": entry, "args": (t, b, old_cells, t_now), "seconds": 0.0,
                             "ages": (self.age.copy(), self.visit.copy())}
            self._window_slice()
            if self._task.done:
                self._conclude_task()
            return
        tic = time.perf_counter()
        entry.update(self.verify(t, b, old_cells, self._n_old))
        self.profile["verify"] += time.perf_counter() - tic
        self._conclude(entry, t, b, old_cells, t_now, time.perf_counter() - tic)

    # ---- sliced verification (real time) ----------------------------------------------------------------------
    def _advance(self, budget: float | None) -> None:
        """Run slices of the task in flight until it ends or ``budget`` wall seconds are used (None: to its end);
        at least one (progress without idle time too)."""
        tic = time.perf_counter()
        while not self._task.done:
            self._task.resume()
            if budget is not None and time.perf_counter() - tic >= budget:
                break
        self._count(time.perf_counter() - tic)

    def _window_slice(self) -> None:
        """The task's slice before a window (none while the back-end is behind: then only idle time advances it)."""
        if not self._idle_only:
            self._advance(self.slice_seconds)

    def _count(self, spent: float) -> None:
        self._pending["seconds"] += spent
        self.profile[self._pending["kind"]] += spent

    def _slice_point(self) -> None:
        """Where a sliced task may pause (no-op otherwise)."""
        task = self._task
        if task is not None and task.in_thread():
            task.pause()

    def _paused(self) -> float:
        """Wall seconds a sliced task spent paused so far (0 offline): not its work."""
        task = self._task
        return task.paused_seconds if task is not None and task.in_thread() else 0.0

    def pending(self) -> bool:
        """A sliced task is in flight and has work left (``idle_slice`` would run some)."""
        return self._task is not None and not self._task.done

    def idle_slice(self) -> None:
        """One slice of the task in flight (the back-end worker calls this while no input waits); its result is
        used before the next window."""
        if self.pending():
            tic, cpu = time.perf_counter(), time.process_time()
            self._task.resume()
            self._count(time.perf_counter() - tic)
            self._spent(tic, cpu)

    def drain(self) -> None:
        """Finish the tasks in flight at once and verify at once from now on (the end of the stream: the results
        apply to the last windows, none is left unfinished)."""
        self._drained = self._drained or self.slice_seconds is not None
        self.slice_seconds = None
        tic, cpu = time.perf_counter(), time.process_time()
        while self._task is not None:
            self._advance(None)
            self._conclude_task()
        self.seconds += time.perf_counter() - tic  # (not a stall of the windows: none follow)
        self.cpu_seconds += time.process_time() - cpu

    def _conclude_task(self) -> None:
        task, pending = self._task, self._pending
        self._task = self._pending = None
        if pending["kind"] == "rebuild":
            tic = time.perf_counter()
            self._task_spline = None
            self._correct(self.backend.spline, pending["correction"])  # the poses initialized meanwhile too
            self._finish_rebuild(*task.result, pending["thinned"])
            self.profile["rebuild"] += time.perf_counter() - tic
            return
        entry = pending["entry"]
        entry.update(task.result)
        entry["sliced"] = True
        self._conclude(entry, *pending["args"], pending["seconds"], pending["ages"])

    def _conclude(self, entry: dict, t, b, old_cells, t_now: float, seconds: float, ages=None) -> None:
        """The decision on a verified candidate: apply it or not; the next check's time; the report entry."""
        cfg = self.cfg
        tic = time.perf_counter()
        px = 2 * np.pi / self.backend.width
        # a joint refinement (at most once per turn of rotation travelled) is worth a rebuild however small the
        # single rotation: it corrects the trajectory between the visits, not one offset
        joint = entry["accepted"] and self._joint_due()
        if entry["accepted"] and not joint and entry["correction_deg"] < np.degrees(cfg.loop_min_correction_px * px):
            entry["applied"], entry["reason"] = False, "correction below loop_min_correction_px"
        elif entry["accepted"] and not joint and entry["confidence"] - entry["confidence_before"] < cfg.loop_min_gain:
            entry["applied"], entry["reason"] = False, "correlation gain below loop_min_gain"
        elif entry["accepted"]:
            entry.update(self._apply(t, b, old_cells, np.asarray(entry.pop("_phi")), t_now, ages, joint))
        entry.pop("_phi", None)
        # while the revisit goes on and the map stays consistent, verify less and less often (up to once per
        # loop_min_age): the cost of a long revisit stays bounded; an applied loop starts again at loop_recent_time
        # after an applied loop, the next one when the drift rate it measured has moved the map by
        # loop_check_drift_px (a verification finding less would not pay for itself), within [recent, loop_min_age]
        recent, longest = cfg.loop_recent_time, max(cfg.loop_min_age, cfg.loop_recent_time)
        if entry.get("applied"):
            drift = cfg.loop_check_drift_px * 2 * np.pi / self.backend.width  # rad
            wait = drift / self._drift_rate if self._drift_rate > 0 else longest
            self._interval = min(max(wait, recent), longest)
        elif entry["reason"] == "correction above loop_max_correction":
            # the registration ran off (at the start of a revisit, with little overlap, the contrast rises by
            # sliding the recent map over more of the old one): it says nothing of the map's consistency, and the
            # overlap grows as the revisit goes on: again after loop_recent_time
            self._interval = recent
        else:
            self._interval = min(2 * self._interval, longest)
        self._next_check = t_now + self._interval
        entry["seconds"] = seconds + time.perf_counter() - tic
        self.loops.append(entry)

    def verify(self, t: np.ndarray, b: np.ndarray, old_cells: np.ndarray, n_aged: int | None = None) -> dict:
        """Register events (times t, bearings b) against the old map on ``old_cells`` alone; the decision.
        ``n_aged``: the chunks aged at detection (the old map's; default all aged so far).

        Returns correction_deg, confidence (correlation at the optimum), confidence_before (at no correction),
        peak_ratio, accepted, reason and ``_phi`` (the correction's rotation vector, world frame, left).
        """
        # a copy: the poses as they are now, also when the verification runs in slices between later windows
        cfg, spline = self.cfg, self.backend.spline.copy()
        w, h = self.backend.width, self.backend.height
        self._vote_aged(self._n_old if n_aged is None else n_aged)
        mask = np.repeat(np.repeat(old_cells, _CELL, axis=0), _CELL, axis=1)[:h, :w]
        rows = np.flatnonzero(mask.any(axis=1))
        if len(rows) == 0:
            return {"correction_deg": 0.0, "confidence": 0.0, "confidence_before": 0.0, "peak_ratio": 0.0,
                    "accepted": False, "applied": False, "reason": "no old map region", "_phi": [0.0, 0.0, 0.0]}
        g_raw = np.zeros((h, w), np.float32)  # the old map on the old regions (zero pages beyond their rows)
        g_rows = slice(int(rows[0]), int(rows[-1]) + 1)
        np.copyto(g_raw[g_rows], self.old.raw[g_rows], where=mask[g_rows])
        base = spline.control_R.copy()
        tic, paused0 = time.perf_counter(), self._paused()
        phi, problem = self._register(t, b, spline, base, g_raw, rows)
        if np.linalg.norm(phi) > cfg.loop_max_correction:  # a false loop: no need to refine it
            return {"correction_deg": float(np.degrees(np.linalg.norm(phi))), "confidence": 0.0,
                    "confidence_before": 0.0, "peak_ratio": 0.0, "accepted": False, "applied": False,
                    "reason": "correction above loop_max_correction", "_phi": phi.tolist()}
        self.profile["register"] += time.perf_counter() - tic - (self._paused() - paused0)
        self._slice_point()
        conf, peak, before = self._confidence(problem, phi, base, mask, rows)
        corr = float(np.linalg.norm(phi))
        if conf < cfg.loop_min_confidence:
            ok, reason = False, "confidence below loop_min_confidence"
        elif peak < cfg.loop_min_peak_ratio:
            ok, reason = False, "optimum not unique (peak ratio below loop_min_peak_ratio)"
        elif corr > cfg.loop_max_correction:
            ok, reason = False, "correction above loop_max_correction"
        else:
            ok, reason = True, "accepted"
        return {"correction_deg": float(np.degrees(corr)), "confidence": conf, "confidence_before": before,
                "peak_ratio": float(peak), "accepted": ok, "applied": False, "reason": reason, "_phi": phi.tolist()}

    def _register(self, t, b, spline, base, g_raw, rows):
        """One rotation phi (left, world frame) registering the events against the old map ``g_raw`` (zero beyond
        ``rows``), coarse to fine; stops at a level whose phi exceeds loop_max_correction. Returns (phi, the finest
        level's PanoIWE problem)."""
        cfg, bcfg = self.cfg, self.backend.cfg
        w, h = self.backend.width, self.backend.height
        mids, _ = self._rotations(t)
        s, u = spline.support(mids)
        phi = np.zeros(3)
        levels = [f for f in (4, 2, 1) if w % f == 0 and h % f == 0 and (w // f >= 256 or f == 1)]
        problem = None
        for f in levels:
            self._slice_point()
            g = _downsample(g_raw, rows, f) if f > 1 else g_raw
            # the old map is zero beyond its rows: density and blur on those rows only (large maps); alpha (Eq. 16-17)
            # from the recent events' local map at the start (the first evaluation: no projection of its own)
            r0, r1 = int(rows[0]) // f, int(rows[-1]) // f + 1
            rho_g = event_density(g[r0:r1], bcfg.lambda0)
            g_blurred, g_sums = _blur_rows(g, r0, r1, bcfg.backend_blur_sigma)
            problem = PanoIWE(b, s, u, bcfg.spline_degree, w // f, h // f, sigma=bcfg.backend_blur_sigma,
                              global_blurred=g_blurred, global_sums=g_sums, alpha=0.0,
                              alpha_from_density=(rho_g, bcfg.lambda0) if rho_g > 0 else None,
                              batch_size=bcfg.event_batch_size)
            scale = []  # 1 / the variance at the level's start: BFGS evaluates there first (no evaluation of its own)

            def objective(x, problem=problem, scale=scale):
                self._slice_point()
                var, grad = problem.cost_and_grad(so3.exp(x) @ base)
                if not scale:
                    scale.append(1.0 / var if var > 0 else 1.0)
                # one common left increment of every control pose moves the whole trajectory by it
                return var * scale[0], so3.left_jacobian(x).T @ grad.sum(axis=0) * scale[0]

            # BFGS from the inverse Hessian the last verification ended with at this level (the same normalized
            # cost of one rotation: its first step is already quasi-Newton, far fewer evaluations than CG)
            px = f * 2 * np.pi / w
            res, hess = bfgs(objective, phi, maximize=True, inv_hessian=self._inv_hessian.get(f), init_step=2 * px,
                             max_iter=_ITERS, grad_tol=bcfg.backend_cg_grad_tol,
                             rel_cost_tol=bcfg.backend_cg_rel_cost_tol, step_tol=_STEP_TOL * px)
            if hess is not None:
                self._inv_hessian[f] = hess
            phi = res.x
            if np.linalg.norm(phi) > cfg.loop_max_correction:
                break
        return phi, problem

    def _confidence(self, problem, phi, base, mask, rows) -> tuple[float, float, float]:
        """(confidence, peak ratio, confidence before): the correlation of the registered recent map with the old
        map over the old regions, its ratio to the best correlation 4 and 8 map pixels away, and the correlation at
        no correction."""
        w, h = self.backend.width, self.backend.height
        # correlation of the registered recent map with the old map over the old regions, on local texture: on the
        # box around them (rows, and the cyclic column interval) with a margin for the texture filter and the shifts
        # (the box of the old regions the registered recent map covers: the correlation reads nothing else)
        margin = 4 * _TEXTURE + int(math.ceil(max(_RING)))
        box_opt = problem.local_box(so3.exp(phi) @ base)
        used = None
        if box_opt is not None:  # the old regions the registered recent map covers, on its box only
            r0, lcols, lmap = box_opt
            both = mask[r0:r0 + len(lmap)][:, lcols] & (lmap > 0)
            if both.any():
                rows_both = r0 + np.flatnonzero(both.any(axis=1))
                used = np.zeros(w, bool)
                used[lcols[both.any(axis=0)]] = True
        if used is None:
            rows_both, used = rows, mask.any(axis=0)
        band = slice(max(int(rows_both[0]) - margin, 0), min(int(rows_both[-1]) + margin + 1, h))
        cols = _cyclic_span(used, margin)
        wrap = len(cols) == w  # the whole width: columns wrap
        at_col = np.full(w, -1)
        at_col[cols] = np.arange(len(cols))

        def crop(box):
            """A local box (PanoIWE.local_box) on the band x cols crop (zero elsewhere)."""
            out = np.zeros((band.stop - band.start, len(cols)))
            if box is not None:
                r0, lcols, lmap = box
                ra, rb = max(r0, band.start), min(r0 + len(lmap), band.stop)
                keep = at_col[lcols] >= 0
                if ra < rb and keep.any():
                    out[ra - band.start:rb - band.start][:, at_col[lcols[keep]]] = lmap[ra - r0:rb - r0][:, keep]
            return out

        g_tex = local_texture(problem.gmap[band][:, cols], _TEXTURE, wrap)
        m_band = mask[band][:, cols]

        def ncc(tex, covered, shift=(0, 0)):
            """Correlation over the old regions of the recent map's texture (shifted by (rows, columns); on the
            pixels its map covers) with the old map's. Sums of products by einsum, not ``@``: a BLAS dot of this
            length runs threaded, and its idle threads spin."""
            if shift != (0, 0):
                covered = np.roll(covered, shift, axis=(0, 1))
                tex = np.roll(tex, shift, axis=(0, 1))
            sel = m_band & covered
            if np.count_nonzero(sel) < 16:
                return 0.0
            a, c = tex[sel], g_tex[sel]
            a, c = a - a.mean(), c - c.mean()
            den = math.sqrt(float(np.einsum("i,i->", a, a)) * float(np.einsum("i,i->", c, c)))
            return float(np.einsum("i,i->", a, c)) / den if den > 0 else 0.0

        def maps_at(box):
            """(texture, covered pixels) of the recent map (a local box)."""
            lmap = crop(box)
            self._slice_point()
            return local_texture(lmap, _TEXTURE, wrap), lmap > 1e-3 * float(lmap.max())

        self._slice_point()
        at_opt = maps_at(box_opt)
        self._slice_point()
        conf = ncc(*at_opt)
        # uniqueness: the registered recent map shifted by _RING map pixels in 4 directions each (a second peak
        # there: repeated texture, a false loop). Shifting the map (not re-voting at rotated poses) costs one
        # correlation each; near the optimum a small rotation moves the map by about such a shift.
        ring = []
        for r in _RING:
            for a in np.arange(4) * np.pi / 2 + (np.pi / 4 if r > _RING[0] else 0.0):
                self._slice_point()
                ring.append(ncc(*at_opt, shift=(int(round(r * math.sin(a))), int(round(r * math.cos(a))))))
        best_ring = max(ring)
        peak = conf / best_ring if best_ring > 0 else np.inf
        self._slice_point()
        return conf, peak, ncc(*maps_at(problem.local_box(base)))

    # ---- correction ----------------------------------------------------------------------------------------------
    def _apply(self, t, b, old_cells, phi, t_now, ages=None, joint: bool = False) -> dict:
        """Spread the correction over the control poses since the old visit (``joint``: then refine them jointly
        with the stored events, ``_joint_refine``); rebuild the maps. ``ages``: the (age, visit) maps at detection
        (None: the current ones)."""
        age, visit = ages if ages is not None else (self.age, self.visit)
        backend = self.backend
        spline = backend.spline
        corr = so3.exp(phi)
        _, rot = self._rotations(t, corr)
        cells = self._cells(b, rot)
        on_old = old_cells.flat[cells]
        if not on_old.any():
            return {"applied": False, "reason": "no recent event on the old map"}
        # the correction was measured by the recent events on the old regions, against the last visit there: the
        # old map of a region stands for the poses of that whole visit, zero correction at its middle
        hit = cells[on_old]
        t_old = float(np.median(0.5 * (visit.flat[hit] + age.flat[hit])))
        t_ref = float(np.median(t[on_old]))
        t_a = max(t_old, self._closed_until)
        if t_ref <= t_a:
            return {"applied": False, "reason": "old visit not before the recent events", "t_old": t_old}
        knots = spline.knot_times()
        i0 = max(int(np.searchsorted(knots, t_a, side="right")) - 1, 0)
        i1 = min(int(np.searchsorted(knots, t_ref, side="left")), len(knots) - 1)
        ctrl = spline.control_R
        # edge weights of the chain pose graph: rotation travelled, plus a little time (drift while nearly still)
        steps = so3.geodesic_angle(ctrl[i0:i1], ctrl[i0 + 1:i1 + 1]) + 0.01 * spline.dt
        correction = (i0, i1, so3.spread_correction(steps, phi), corr)
        joint_info = None
        if joint:
            self._joint_travel = float(self._travel_rec[1, self._n_travel - 1])
            joint_info = {"coverage": self._coverage_since(self._joint_time) if self.joint_refinements else 1.0}
            self._joint_time = float(t_now)
            self.joint_refinements += 1
        if self.slice_seconds is None:
            if joint:
                correction = self._joint_refine(correction, joint_info)
            self._correct(spline, correction)
            self._rebuild()
        else:  # in slices too, along a corrected copy; the back-end keeps its poses and maps (consistent with
            # each other, for the BA of the windows meanwhile) until the rebuilt maps replace them with the correction
            n_old, thinned = self._n_old, self._thinned
            n_chunks = len(self.chunks)  # the strides the copy holds poses for
            pending = {"kind": "rebuild", "n_old": n_old, "thinned": thinned, "seconds": 0.0, "correction": correction}

            def refine_and_rebuild():
                if joint:
                    pending["correction"] = self._joint_refine(pending["correction"], joint_info)
                self._task_spline = self._correct(self.backend.spline.copy(), pending["correction"])
                return self._rebuild_in_slices(n_old, n_chunks)

            self._task, self._pending = _Slices(refine_and_rebuild), pending
            self._window_slice()
        self._closed_until = float(t[-1])
        # the drift since the old visit or the last loop's reference time (from which the poses carried its whole
        # correction): its rate schedules the next check (_conclude)
        self._drift_rate = float(np.linalg.norm(phi)) / max(t_ref - max(t_old, self._ref), 1e-3)
        self._ref = t_ref
        out = {"applied": True, "reason": "accepted", "t_old": t_old, "t_ref": t_ref, "t_spread_from": float(knots[i0])}
        if joint_info is not None:
            out["joint"] = joint_info  # (filled in when a sliced refinement ends)
        return out

    def _joint_due(self) -> bool:
        """A joint refinement at most once per full turn: after 360 deg of rotation travelled and once the camera
        observed again at least ``_JOINT_COVERAGE`` of the map's observed columns since the last refinement (a pan's
        wobble adds rotation travelled, not turns; before the camera comes round again the stored events hold little
        the last refinement did not, and a slow revisit that goes on for seconds does not repeat it)."""
        if not self.cfg.loop_joint_refinement:
            return False
        if float(self._travel_rec[1, self._n_travel - 1]) - self._joint_travel < 2 * math.pi:
            return False
        return self.joint_refinements == 0 or self._coverage_since(self._joint_time) >= _JOINT_COVERAGE

    def _coverage_since(self, t: float) -> float:
        """The fraction of the map's observed columns (of age cells) observed again at or after time t."""
        seen = np.count_nonzero((self.age > -np.inf).any(axis=0))
        return np.count_nonzero((self.age >= t).any(axis=0)) / seen if seen else 0.0

    def _joint_refine(self, correction, info: dict):
        """The loop's correction refined jointly (``joint_refinement.refine_jointly``): from the chain spread, the
        control poses from the first stored stride on (every visit the store holds; the first pose anchors the
        world frame) with the stored strides, coarse: increments interpolated between nodes every 5 window lengths
        (the window BA fixes the motion within a window, the errors it leaves vary over many; every pose free
        would also fit the noise of the sampled events between the nodes), at zero mean over the nodes (only the
        first pose holds the world frame: the refinement redistributes the errors, ``hold_mean``), then the start
        (``_refine_start``, unless ``loop_joint_start_span`` is 0 or the store does not reach back to it); returns
        the correction in the same form (poses 0..last get theirs, later ones the last one's) and fills ``info``."""
        tic, paused0 = time.perf_counter(), self._paused()
        i0, i1, spread, corr = correction
        spline = self._correct(self.backend.spline.copy(), correction)
        knots = spline.knot_times()
        first = min(int(np.searchsorted(knots, float(self.chunks[0][0][0]) if self.chunks else knots[0])), i0)
        last = spline.num_control - 1
        if self.chunks:  # the last pose the stored strides reach; later poses follow it rigidly
            s_end, _ = spline.support(min(float(self.chunks[-1][0][-1]), spline.valid_time_range()[1]))
            last = min(max(int(np.max(s_end)) + spline.degree, i1), last)
        bcfg, cfg = self.backend.cfg, self.cfg
        x, summary = refine_jointly(spline, list(self.chunks), first, last, bcfg, self.backend.width,
                                    self.backend.height, max_events=cfg.loop_joint_events,
                                    iterations=cfg.loop_joint_iterations,
                                    coarse_spacing=5 * bcfg.backend_time_window_size,
                                    max_step=cfg.loop_max_correction, slice_point=self._slice_point, hold_mean=True)
        eye = np.broadcast_to(np.eye(3), (i0 - first, 3, 3))
        chain = np.concatenate([eye, spread, np.broadcast_to(corr, (max(last - i1, 0), 3, 3))])[:last - first + 1]
        turns = np.concatenate([np.broadcast_to(np.eye(3), (first, 3, 3)), so3.exp(x) @ chain])  # poses 0..last
        after = so3.exp(x[-1]) @ corr
        if cfg.loop_joint_start_span > 0 and self.chunks and self.chunks[0][3] <= self.backend.t_start + 1e-9:
            joint = self._correct(spline, (first, last, so3.exp(x), so3.exp(x[-1])))  # the joint refinement's poses
            turns, after, info["start"] = self._refine_start(joint, turns, after, last)
        info.update(summary, seconds=time.perf_counter() - tic - (self._paused() - paused0))
        if self.slice_seconds is None:  # (sliced: counted with the rebuild task it runs in)
            self.profile["joint"] += info["seconds"]
        return 0, last, turns, after

    def _refine_start(self, spline, turns, after, last: int):
        """The joint refinement's result (left rotations ``turns`` of poses 0..last, ``after`` of the later ones,
        turning the back-end's spline into ``spline``, which this changes) with the start of the trajectory
        registered against the map of the later stored events (``joint_refinement.refine_start``; the later poses
        hold the world frame); returns them and a summary. At every joint refinement: the later turns' loops and
        refinements keep moving the rest against the start."""
        backend, cfg = self.backend, self.cfg
        bcfg = backend.cfg
        y, info = refine_start(spline, list(self.chunks), bcfg.backend_min_ev_rate * bcfg.backend_time_window_size,
                               bcfg.backend_sliding_window_stride, cfg.loop_joint_start_span, bcfg, backend.width,
                               backend.height, max_events=cfg.loop_joint_events, iterations=cfg.loop_joint_iterations,
                               max_step=cfg.loop_max_correction, slice_point=self._slice_point)
        turns = turns.copy()
        turns[:len(y)] = so3.exp(y) @ turns[:len(y)]
        return turns, after, info

    def _correct(self, spline, correction):
        """Apply a loop's correction (i0, i1, spread rotations of poses i0..i1, rotation of the later poses) to a
        spline's control poses (and, on the back-end's, re-anchor its source poses); returns the spline."""
        i0, i1, spread, corr = correction
        def rotate(spl):
            ctrl = spl.control_R
            ctrl[i0:i1 + 1] = spread @ ctrl[i0:i1 + 1]
            ctrl[i1 + 1:] = corr @ ctrl[i1 + 1:]

        if spline is self.backend.spline:
            self.backend.correct_poses(rotate)
        else:
            rotate(spline)
        return spline

    def _rebuild(self) -> None:
        """Global map, old map and age map from the stored subsamples along the (corrected) spline.

        The old map and the age map are rebuilt from the checkpoint the last rebuild left (its maps after aging
        its chunks, and the control poses then) when the correction left the poses of those chunks unchanged:
        every later loop closes only the drift since the last one (``_apply``), so only the chunks aged since are
        voted again, not every chunk since the start. Same votes in the same order: the same maps, bit for bit.
        """
        tic = time.perf_counter()
        n_old = self._n_old
        self.backend.drop_map()  # free the old maps first: peak memory holds one set (+ the checkpoint)
        self.old = None
        self._finish_rebuild(self._rebuild_old(n_old), n_old, None, 0, self._thinned)
        self.profile["rebuild"] += time.perf_counter() - tic

    def _rebuild_in_slices(self, n_old: int, n_chunks: int):
        """The rebuild's bulk as a sliced task, along the corrected copy of the spline: the old maps of
        chunks[:n_old], then of the chunks aged since, and the votes of the recent ones (up to n_chunks, the
        strides the copy has poses for) on a copy of that old map (the global map's raw votes); returns
        _finish_rebuild's arguments (it adds what was aged or stored after this)."""
        maps = self._rebuild_old(n_old)
        n_aged = n_old
        while n_aged < min(self._n_old, n_chunks):  # aged meanwhile (read between slices: the back-end is paused)
            self._slice_point()
            self._age_chunk(self.chunks[n_aged], maps)
            n_aged += 1
        if self._freeze:
            return maps, n_aged, None, 0
        acc = maps[0].copy()
        n_voted = max(min(len(self.chunks), n_chunks), n_aged)
        for t, b, weight, _t0, _moving in self.chunks[n_aged:n_voted]:
            self._slice_point()
            acc.add(b, self._rotations(t)[1], self.backend.cfg.event_batch_size, weight=weight)
        return maps, n_aged, acc, n_voted

    def _rebuild_old(self, n_old: int):
        """(old map, age map, visit map) of chunks[:n_old] along the spline: from the checkpoint when it holds
        unchanged poses, else from scratch (new maps: the current ones stay in use while this runs in slices)."""
        w, h = self.backend.width, self.backend.height
        start = self._checkpoint_start(n_old)
        if start > 0:
            raw, age, visit = self._checkpoint[1:4]
            maps = (_RawMap(w, h, raw=raw.copy()), age.copy(), visit.copy())
        else:
            maps = (_RawMap(w, h), np.full_like(self.age, -np.inf), np.full_like(self.visit, -np.inf))
        for chunk in self.chunks[start:n_old]:
            self._slice_point()
            self._age_chunk(chunk, maps)
        return maps

    def _finish_rebuild(self, maps, n_old: int, acc, n_voted: int, thinned: int) -> None:
        """Take the rebuilt (old, age, visit) maps of chunks[:n_old] (aging the chunks aged since), keep them as
        the checkpoint, and set the global map: the old map plus the recent strides' votes (``acc``: a copy of
        the old map of chunks[:n_old] holding the votes of chunks[n_old:n_voted] already; None: none yet). The
        same additions in the same order either way: the same maps."""
        backend = self.backend
        for chunk in self.chunks[n_old:self._n_old]:  # aged while the rebuild ran in slices
            self._age_chunk(chunk, maps)
        self.old, self.age, self.visit = maps
        self._n_voted = self._n_old  # every aged chunk voted along the corrected poses
        self._rot_cache.clear()
        self._checkpoint = (self._n_old, self.old.raw.copy(), self.age.copy(), self.visit.copy(),
                            backend.spline.control_R.copy(), thinned)
        backend.drop_map()  # (offline, already dropped by _rebuild): rebuilt when the back-end asks (rebuilt_map)
        self.map_stale, self._acc = True, (acc, n_voted) if acc is not None else None

    def rebuilt_map(self) -> GlobalMap:
        """The global map after the last correction (the back-end asks once it dropped its map): the old map plus
        the strides stored since, blurred once (GlobalMap.set_raw); with pixel freezing every stored stride in order.
        The strides the back-end settled meanwhile went into the store only (a dropped map is not voted), so several
        loops between two reads (BA skipped) cost one rebuild. Asked right after the correction (a BA follows it),
        the same votes in the same order as rebuilding at once."""
        tic, cpu = time.perf_counter(), time.process_time()
        bs = self.backend.cfg.event_batch_size
        acc, n_voted = self._acc if self._acc is not None else (None, 0)
        self.map_stale, self._acc = False, None
        gmap = self._new_map()
        if self._freeze:  # first-seen times: every stride in time order, as the back-end settled them
            for t, b, weight, t0, moving in self.chunks:
                gmap.add(b, self._rotations(t)[1], bs, t0, moving, weight=weight)
        else:  # the global map is the old map plus the recent strides' votes: one blur at the end (GlobalMap.set_raw)
            if acc is None:
                if self._task is None:  # (a sliced verification in flight votes the aged chunks itself)
                    self._vote_aged(self._n_old)
                acc, n_voted = self.old.copy(), self._n_voted
            for i in range(n_voted, len(self.chunks)):  # aged ones not voted yet along their cached rotations
                t, b, weight, _t0, _moving = self.chunks[i]
                rot = self._rot_cache.get(i) if i < self._n_old else None
                acc.add(b, self._rotations(t)[1] if rot is None else rot, bs, weight=weight)
            gmap.set_raw(acc.raw)
        self.map_rebuilds += 1
        self.profile["rebuild"] += time.perf_counter() - tic
        self._spent(tic, cpu)
        return gmap

    def _advance_checkpoint(self) -> None:
        """Before the first stride a later loop may move is aged: the maps now hold the last rebuild's checkpoint
        plus strides whose poses no later loop changes (before the last applied loop's recent block end, less the
        spline's support: a later loop spreads from there on), so they become the checkpoint. The next rebuild
        then votes only the strides since the loop again, not the whole recent block before it (a few copies of the
        maps cost less than voting those strides again)."""
        ck = self._checkpoint
        if ck is None or self._task is not None or ck[0] >= self._n_old or ck[5] != self._thinned:
            return
        spline = self.backend.spline
        final = self._closed_until - (spline.degree + 2) * spline.dt
        if self.chunks[self._n_old - 1][0][-1] >= final or self.chunks[self._n_old][0][-1] < final:
            return  # not at the first stride a later loop may move
        self._vote_aged(self._n_old)  # the checkpoint holds the votes of the chunks it counts
        self._checkpoint = (self._n_old, self.old.raw.copy(), self.age.copy(), self.visit.copy(),
                            spline.control_R.copy(), self._thinned)
        self.checkpoints_advanced += 1

    def _checkpoint_start(self, n_old: int | None = None) -> int:
        """Chunks the checkpoint holds when none of their poses changed since it was taken and it holds at most
        n_old (default: all aged; 0: rebuild all)."""
        if self._checkpoint is None:
            return 0
        n, _raw, _age, _visit, ctrl, thinned = self._checkpoint
        spline = self._spline()
        n_old = self._n_old if n_old is None else n_old
        if thinned != self._thinned or n > n_old or n == 0 or len(ctrl) > spline.num_control:
            return 0
        changed = np.flatnonzero(np.any(spline.control_R[:len(ctrl)] != ctrl, axis=(1, 2)))
        k = int(changed[0]) if len(changed) else len(ctrl)
        # R(t) depends on control poses s .. s + degree (SO3Spline.support): times before this one kept theirs
        lead = (spline.degree - 1) // 2
        t_changed = spline.t0 + (k - spline.degree + lead) * spline.dt
        return n if float(self.chunks[n - 1][0][-1]) < t_changed else 0

    # ---- report ----------------------------------------------------------------------------------------------------
    def summary(self) -> dict:
        return {"candidates": len(self.loops), "accepted": sum(e["accepted"] for e in self.loops),
                "applied": sum(bool(e.get("applied")) for e in self.loops), "seconds": self.seconds,
                "cpu_seconds": self.cpu_seconds, "unfinished": int(self._task is not None),
                "longest_call_seconds": self.longest_call[0], "longest_call_cpu_seconds": self.longest_call[1],
                "stored_events": int(self._stored), "map_rebuilds": self.map_rebuilds,
                "joint_refinements": self.joint_refinements,
                "seconds_by_part": dict(self.profile)}
