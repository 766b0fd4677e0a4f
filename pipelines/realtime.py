"""Real-time replay of a recording (``ti-cmax slam --realtime``) and the degradation controller that bounds the lag.

Replay: the file is read in chunks of ``READ_EVENTS`` events (memory does not grow with the file), each chunk is
checked and hot-pixel filtered as it is read (``OnlineSlam.screen``) and each event that passes is handed to
:class:`~ti_cmax.pipelines.slam.OnlineSlam` (``push_screened``) once the wall clock reaches its timestamp
(``realtime_speed`` sensor seconds per wall second). While the system keeps up, the replay sleeps until the next
``realtime_chunk`` of sensor time is due and pushes it; when it is behind, it pushes the due events without waiting
(``HAND_OVER_EVENTS`` per push). No busy waiting. The first chunk is read before the clock starts: its event rate
prepares the back-end's event memory (``OnlineSlam.prepare``), whose first writes would otherwise be page faults in
the first seconds of the replay.

Lag: how far the processing is behind its input. When a window completes (wall time ``done``), lag = done -
due(window end) - dead(window end), where due(t) is the wall time at which sensor time t was handed over in an ideal
replay and dead(t) the time without events that the result at t had to wait through: a window completes only once
the front-end has a packet at or after its end, which takes events after it, so a window ending in or just before a
pause of the stream completes only once the first event after the pause is handed over; the system cannot know
earlier that time went on. A pause is a gap between two events longer than the front-end's still window W =
still_span_factor x dt_ang_vel; the replay records each one as (a, b): its last event before and first after, and the
front-end's last packet time fe before b was handed over. dead(t) = sum of (b - max(a, t)) / speed over the pauses
with b > t and fe < t. So a system still busy with the events before a pause keeps its lag, and the catch-up after a
pause (its packets and windows, processed once it ends) counts as lag.

The latency from an event to its first refined pose is that window's lag plus the event's age within the window's
new stride (mean over time: lag + stride / 2; max: lag + stride).

Controller (one rule, applied after every completed window, with lag L, target T = ``realtime_target_lag`` and
bound M = ``realtime_max_lag``): degradation level l in 0..4, passed to OnlineSlam.degrade (the front-end's packets
and the back-end's ``WindowBudget``):

    l | front-end packets | BA events per window (cap c: backend_max_window_events; floor: realtime_min_window_events)
    0 | all               | c on every window (the offline computation; the BA budget T / 2, below)
    1 | all               | c on every window, with the BA's time budget (below); from level 1 on, the loop
      |                   |   closer's work in flight (a verification, a map rebuild) gets no slice before each
      |                   |   window, only the worker's idle time (a loop closed a few seconds later costs no event)
    2 | all               | c / 2 on every window
    3 | 1 of 2            | c / 2 on 1 of 2 windows
    4 | 1 of 4            | BA skipped (the window keeps the integrated front-end's poses; its events still go
                          |   into the map)

At levels 1-4 a window's BA has a time budget of one stride of sensor time in wall seconds (``ba_budget``): it starts
no BFGS iteration after it and keeps its best point so far (report: ``ba_windows_cut_short``); a BA that needs longer
(a cold start without carried curvature) would otherwise add its excess to the lag at once. At level 0 the budget is
half the lag target: a window completes one BA after its end is due, so a longer BA puts the lag near the target by
itself. A large target leaves level 0 the offline computation.

The levels cut the cheapest computation first: the budget touches only slow windows, then fewer BA events, then fewer
BA windows (the BA's cost is mostly per evaluation over the window's map region, not per event). A window without its
BA (level 3: every other one) settles its stride with the poses the previous window refined (that stride was the
second half of the previous window), so each stride is still refined once.

- L > T and L would not be back under T within ``DRAIN_WINDOWS`` windows at its current rate of change: l += 1 (but
  within ``DRAIN_WINDOWS`` windows of a rise only while L is above the lag at that rise: the windows already queued in
  the worker were sent with the old budget, so a lower level shows only windows later, and a lag that stopped
  rising is its effect; escalating again meanwhile cut events a burst did not need cut), and never on a window
  that ended before the front-end's progress at the last rise while L < (T + M) / 2 (it was sent to the worker
  under the old budget; with a lag L some L / stride windows are in flight: escalating on them would reach the last
  level before the first rise could show); at
  l = 4, the same condition hands over only 1 of q events (q doubles, at most ``MAX_INPUT_THINNING``) and the
  front-end's packets take N / q events (their span kept). A falling lag is given time to drain: a backlog takes
  windows to clear even once the system is faster than the sensor.
- L > M: l = 4 at once.
- Relaxing, on the measured headroom: the cost of a level is the wall time a process works per wall second of sensor
  data, c = busy / (stride / speed), measured per window for the back-end worker (``WindowReport.busy_seconds``) and
  for the main process (wall time not sleeping nor waiting for the worker); with one process, the main process's
  alone. Of the cost, the parts the next lower level changes are measured too: the BA's wall time (scaled by the
  ratio of BA windows and the square root of the ratio of BA events, an overestimate; from level 4 the median of the
  last ``RELAX_WINDOWS`` BAs) and the front-end's (scaled by the ratio of packets). When L < T, L would stay under T
  within ``DRAIN_WINDOWS`` windows, and the predicted cost of l - 1 is below ``RELAX_HEADROOM`` (the rest is left
  for event-rate bursts and other load; ``RELAX_HEADROOM_LOW_LAG`` while L < T / 2, whose slack absorbs bursts for
  several windows) in every process whose work the level changes (with a worker: the worker alone, as the levels
  degrade only the BA there): first q halves (while q > 1 only when L < T / 2), then l -= 1 (at least
  ``RELAX_WINDOWS`` windows after the last change).

The front-end's lag (now - due(t) - dead(t), t the time of its last packet), taken once per stride of its progress,
is a second input to the escalating rules: when the front-end is the bottleneck, windows complete too rarely to react
in time; an escalation it causes goes on to the next level that changes the front-end's work. Front-end packets are
skipped rather than thinned because their cost is mostly per evaluation. With a back-end worker the front-end has a
core of its own, and the two processes fall behind for different reasons, so each degrades its own work: the levels'
front-end column does not apply; the front-end's lag alone (the same escalating test) makes it skip packets, 1 of
``FE_KEEPS`` (2, then 4), then thin the input (q doubles), beyond M at once to 1 of 4; the levels degrade only the
BA and rise only on windows late while the front-end keeps up (a window waiting for a front-end that is behind would
not come sooner with a cheaper BA: escalating then took the BA to level 4 and its events to none while the worker
had room). A front-end that waited for the worker (the backlog bound) since the last decision is late because of the
BA: then its lag changes nothing and the windows' lag rules as without a worker. Relaxing goes in the same order
backwards: q halves, then the front-end skips half as many packets once its lag is under T / 2 and the main process
is predicted to cost under RELAX_HEADROOM with them, then the level falls.
report.json's "realtime" block says how long each level was in force (in sensor seconds) and what it removed.
"""
from __future__ import annotations

import itertools
import math
import time
from typing import Iterable, Iterator

import numpy as np

from ti_cmax.camera import Camera
from ti_cmax.config import SlamConfig
from ti_cmax.errors import InputError
from ti_cmax.events import Events
from ti_cmax.kernels import runtime
from ti_cmax.progress import progress

from .frontend import every_qth
from .sensor_defaults import resolve_config

# events per read of the file (the HDF5 reader's block, 0.16 s at 12.6 M events/s): each read chunk is checked and
# hot-pixel filtered at once (OnlineSlam.screen), while the events just read and the filter's per-pixel counts are in
# the cache (measured on VGA: 2 M-event chunks cost 3 ns per event less than 0.4 M-event ones)
READ_EVENTS = 2_000_000
HAND_OVER_EVENTS = 50_000  # events per hand-over at most (behind schedule): a few ms of data at 10 M events/s
MAX_LEVEL = 4
MAX_INPUT_THINNING = 16  # deeper thinning leaves front-end packets too sparse (their cost is per packet anyway)
RELAX_WINDOWS = 3  # windows at a level before it may be lowered (and over which its costs are averaged)
RELAX_HEADROOM = 0.8  # a level is relaxed only when the lower one is predicted to cost below this (per process)
RELAX_HEADROOM_LOW_LAG = 0.95  # ... or below this while the lag is under half the target
# a loop verification (loop closure) runs in slices: at most this share of a stride's wall time before each window
# (what RELAX_HEADROOM leaves), plus the back-end worker's idle time; at once it would stall the back-end for seconds
# and break the lag bound
LOOP_SLICE_SHARE = 1.0 - RELAX_HEADROOM
# the controller's per-window trace (``ti-cmax slam --realtime`` writes it as realtime_windows.csv): what it read and
# what it decided, the figures behind every real-time tuning in this module's docstring
TRACE_COLUMNS = ("t_start", "t_end", "lag_s", "level", "input_thinning", "events", "ba_events", "ba_seconds",
                 "ba_evaluations", "ba_cut_short", "ba_skipped", "worker_busy_seconds", "frontend_lag_s", "next_level")
DRAIN_WINDOWS = 5  # a lag above target that falls back under it within this many windows needs no escalation
# level -> (1 of k front-end packets, BA cap divisor (0: BA skipped), BA on 1 of m windows)
LEVELS = {0: (1, 1, 1), 1: (1, 1, 1), 2: (1, 2, 1), 3: (2, 2, 2), 4: (4, 0, 1)}  # level 1: the BA budget only
FE_KEEPS = (1, 2, 4)  # with a worker: the front-end's own steps (1 of k packets), taken on its lag alone


class RealtimeController:
    """The controller of the module docstring: reads the lag of each completed window, sets OnlineSlam's
    degradation, keeps the figures of the report's "realtime" block."""

    def __init__(self, config: SlamConfig, speed: float, worker: bool = False):
        rt, be = config.realtime, config.backend
        # with a back-end worker the front-end has a core of its own: its packets are skipped (1 of FE_KEEPS[fe_level])
        # by a rule of its own, only while it falls behind, and the levels degrade the BA alone (module docstring)
        self.worker = worker
        self.fe_level = 0
        self.target, self.bound, self.speed = rt.realtime_target_lag, rt.realtime_max_lag, speed
        self.stride = be.backend_sliding_window_stride
        self.cap = be.backend_max_window_events  # -1: every event (then the divisors apply to the window's count)
        self.floor = rt.realtime_min_window_events
        self.online = None
        self.level, self.thinning = 0, 1
        self._since_change = 0
        self._lag_at_change = -math.inf  # the windows' lag when the level last rose (a newer level is given time)
        # the front-end's progress when the level or the thinning last rose: windows ending by then were sent to the
        # worker under the old budget, so they cannot show the new one's effect
        self._rise_sent: float | None = None
        self.wall0 = self.t0 = None
        self.lags: list[float] = []
        self.latency_mean: list[float] = []
        self.latency_max: list[float] = []
        self.level_seconds = [0.0] * (MAX_LEVEL + 1)  # sensor seconds of windows completed at each level
        self.thinned_seconds = 0.0
        self.max_thinning = 1
        self._prev_end = None
        self._prev_lag: dict[str, float] = {}  # last lag per source ("window", "frontend")
        self._fe_tick = self._fe_lag = None
        self._window_events = None
        self.ba_used = self.ba_offline = 0  # BA events used, and what the offline run would use
        self.windows_skipped = self.windows_sampled = self.windows_cut = 0
        # headroom (module docstring): per-window costs at the current level, the main process's idle time
        # (sleeping until events are due + waiting for the worker; set by run_realtime) and the BA's seconds/event
        self.idle_seconds = lambda: 0.0
        # wall seconds the main process waited for the worker so far (set by run_realtime): a front-end held back by
        # the worker (its backlog bound) is late because of the BA, not its own work
        self.blocked_seconds = lambda: 0.0
        self._blocked_at: dict[str, float] = {}  # blocked_seconds() at the last decision per source
        self._costs: list[dict] = []  # per window since the last change: {"worker", "main", "ba", "fe"}
        self._mark = None  # (time.monotonic, main idle, front-end seconds, front-end time, worker done_at)
        self._ba_recent: list[tuple[float, int]] = []  # (seconds, events) of the last RELAX_WINDOWS windows with a BA
        self.predicted: list[float] = []  # predicted cost of the level below at each relaxation (report)
        self.trace: list[tuple] = []  # one row per completed window (TRACE_COLUMNS): realtime_windows.csv
        # pauses of the stream (module docstring, Lag), recorded by run_realtime: (last event before, first event
        # after, frontend_until just before that one was handed over)
        self.pauses: list[tuple[float, float, float | None]] = []

    def due(self, t: float) -> float:
        """Wall time (time.monotonic) at which sensor time t is handed over."""
        return self.wall0 + (t - self.t0) / self.speed

    def dead(self, t: float) -> float:
        """Wall seconds of the pauses after sensor time t that the result at t had to wait through (module
        docstring, Lag): those that end after t and whose end was handed over before the front-end reached t."""
        return sum(b - max(a, t) for a, b, fe in self.pauses if b > t and (fe is None or fe < t - 1e-9)) / self.speed

    def ba_cap(self, level: int, window_events: int | None = None) -> int | None:
        divisor = LEVELS[level][1]
        if divisor == 1:
            return None
        if divisor == 0:
            return 0
        base = self.cap if self.cap > 0 else (window_events or self.floor)
        return int(max(self.floor, base // divisor))

    @property
    def fe_skipping(self) -> bool:
        """The front-end skips packets (with a worker: by its own rule)."""
        return self.fe_keep() > 1

    def fe_keep(self, level: int | None = None) -> int:
        """1 of this many front-end packets is processed at ``level`` (default: the current one; with a worker the
        front-end's own rule sets it, whatever the level)."""
        if self.worker:
            return FE_KEEPS[self.fe_level]
        return LEVELS[self.level if level is None else level][0]

    def _frontend_fits_less_skipped(self) -> bool:
        """The main process would cost under RELAX_HEADROOM with the front-end skipping half as many packets (its
        measured front-end part scaled to them)."""
        mean = self.mean_costs()
        if mean is None or self.fe_level == 0:
            return False
        ratio = FE_KEEPS[self.fe_level] / FE_KEEPS[self.fe_level - 1]
        return mean["main"] + mean["fe"] * (ratio - 1) < RELAX_HEADROOM

    def ba_budget(self) -> float:
        """Seconds a window's BA may take at the current level (module docstring): half the lag target at level 0,
        else one stride of sensor time in wall seconds (a BA that needs longer, e.g. a cold start without carried
        curvature, would add its excess to the lag; it keeps its best point)."""
        return 0.5 * self.target if self.level == 0 else self.stride / self.speed

    def on_window(self, report) -> None:
        """After every completed window: record lag and latency, then apply the rule."""
        if self.wall0 is None:
            return
        end = report.t_end
        prev = self._prev_end if self._prev_end is not None else report.t_start
        lag = report.done_at - self.due(end) - self.dead(end)
        self.pauses = [p for p in self.pauses if p[1] > end]  # later windows and packets are past them
        self.lags.append(lag)
        new = max(end - prev, 0.0) / self.speed
        self.latency_mean.append(lag + 0.5 * new)
        self.latency_max.append(lag + new)
        self._prev_end = max(end, prev)
        span = report.t_end - report.t_start
        self.level_seconds[self.level] += min(self.stride, span)
        if self.thinning > 1:
            self.thinned_seconds += min(self.stride, span)
        if report.optimized or report.rejected or report.skipped:
            offline = report.num_events if self.cap < 0 else min(report.num_events, self.cap)
            self.ba_offline += offline
            self.ba_used += report.events_used
            self.windows_skipped += int(report.skipped)
            self.windows_sampled += int(0 < report.events_used < offline)
            self.windows_cut += int(report.cut_short)
        self._window_events = report.num_events
        self._measure(report)
        level, thinning = self.level, self.thinning  # in force while this window ran
        self._control(lag, t_end=end)
        self.trace.append((report.t_start, end, lag, level, thinning, report.num_events, report.events_used,
                           report.ba_seconds, report.evaluations, int(report.cut_short), int(report.skipped),
                           report.busy_seconds, self._fe_lag, self.level))

    def _measure(self, report) -> None:
        """Costs (wall seconds of work per wall second of sensor data) of this window at the current level."""
        online = self.online
        fe_seconds = online.runner.seconds if online is not None else 0.0
        fe_time = online.frontend_until if online is not None else None
        now, idle = time.monotonic(), self.idle_seconds()
        mark, self._mark = self._mark, (now, idle, fe_seconds, fe_time, report.done_at)
        if report.ba_seconds > 0 and report.events_used > 0:
            self._ba_recent = (self._ba_recent + [(report.ba_seconds, report.events_used)])[-RELAX_WINDOWS:]
        if mark is None or fe_time is None or mark[3] is None:
            return
        sensor = self.stride / self.speed  # per window: one stride of sensor data, in wall seconds
        # wall seconds of work and of sensor data; costs are ratios of sums over windows (callbacks come in bursts
        # when the main process catches up, so per-window ratios would be noisy)
        cost = {"main": (max(0.0, (now - mark[0]) - (idle - mark[1])), (fe_time - mark[3]) / self.speed),
                "fe": (fe_seconds - mark[2], (fe_time - mark[3]) / self.speed), "ba": (report.ba_seconds, sensor),
                "worker": (report.busy_seconds, sensor) if report.busy_seconds is not None else None}
        if report.busy_seconds is None:  # one process: the back-end's step is part of the main process's work
            cost["main"] = (max(cost["main"][0], report.seconds + cost["fe"][0]), cost["main"][1])
        self._costs.append(cost)

    def mean_costs(self) -> dict | None:
        """Costs of the current level over its last windows covering RELAX_WINDOWS strides of the front-end's
        progress (windows complete in bursts when the main process catches up: counting windows would divide by
        almost no sensor time): {"main", "fe", "ba", "worker"}; None until that much was measured."""
        need = RELAX_WINDOWS * self.stride / self.speed * (1 - 1e-6)
        sums = None
        for cost in reversed(self._costs):
            sums = {k: [a + b for a, b in zip(sums[k], v)] if v is not None else None
                    for k, v in cost.items()} if sums is not None else {k: list(v) if v is not None else None
                                                                          for k, v in cost.items()}
            if sums["main"][1] >= need:
                break
        if sums is None or sums["main"][1] < need:
            return None
        return {k: v[0] / max(v[1], 1e-9) if v is not None else None for k, v in sums.items()}

    def predicted_cost(self) -> float | None:
        """Predicted cost of the level below the current one in its costliest process (module docstring), from
        the mean costs of the windows since the last change; None before any was measured."""
        mean = self.mean_costs()
        if mean is None or self.level == 0:
            return None
        lower = self.level - 1
        cap_now, cap_lower = self.ba_cap(self.level, self._window_events), self.ba_cap(lower, self._window_events)
        full = self.cap if self.cap > 0 else (self._window_events or self.floor)
        cap_now = full if cap_now is None else cap_now
        cap_lower = full if cap_lower is None else cap_lower
        # BA cost per window ~ sqrt(events): sub-linear, as per-evaluation work over the map region weighs most
        every_now, every_lower = LEVELS[self.level][2], LEVELS[lower][2]
        if cap_now > 0:
            ba_lower = mean["ba"] * math.sqrt(cap_lower / cap_now) * every_now / every_lower
        elif self._ba_recent:  # no BA at this level: the last ones measured (median: one slow window, e.g. the cold
            # first one or one after skipped strides, would keep the controller at level 4), at the lower level's cap
            per_root_event = float(np.median([sec / math.sqrt(ev) for sec, ev in self._ba_recent]))
            ba_lower = per_root_event * math.sqrt(cap_lower) / every_lower / (self.stride / self.speed)
        else:
            ba_lower = 0.0
        fe_lower = mean["fe"] * self.fe_keep(self.level) / self.fe_keep(lower)
        main = mean["main"] + (fe_lower - mean["fe"])
        if mean["worker"] is None:  # one process does both
            return main + (ba_lower - mean["ba"])
        # with a worker the levels change the BA alone (the front-end's skipping has its own rule): the main
        # process's cost stays what it is, however busy a high event rate keeps it
        return mean["worker"] + (ba_lower - mean["ba"])

    def on_frontend(self, now: float, t: float | None) -> None:
        """After every push: the front-end's lag (now - due(its last packet's time)), once per stride of its progress
        or of wall time, whichever comes first, is the rule's second input (a slow front-end delays the windows, so
        they alone would react late; and a front-end several times slower than the sensor takes several strides of
        wall time per stride of progress). It only escalates: relaxing waits for windows."""
        if t is None or self.wall0 is None:
            return
        if self._fe_tick is not None and t < self._fe_tick[0] + self.stride \
                and now < self._fe_tick[1] + self.stride / self.speed:
            return
        self._fe_tick = (t, now)
        self._fe_lag = now - self.due(t) - self.dead(t)
        self._control(self._fe_lag, "frontend")

    def relax_headroom(self, lag: float) -> float:
        """The predicted cost under which a level may be relaxed: RELAX_HEADROOM, or RELAX_HEADROOM_LOW_LAG while the
        lag is under half the target (that slack absorbs the lower level's bursts for several windows; a lower level
        that does not fit shows as a rising lag and is escalated again)."""
        return RELAX_HEADROOM_LOW_LAG if lag < 0.5 * self.target else RELAX_HEADROOM

    def _control(self, lag: float, source: str = "window", t_end: float | None = None) -> None:
        old = (self.level, self.thinning, self.fe_level)
        # a window sent to the worker before the last rise ran under the old budget: it shows nothing of the new one
        # (with a lag of L, some L / stride windows are in flight), so it escalates no further while the lag stays
        # within halfway from the target to the bound (beyond, an overload the rise cannot absorb in time)
        judged = source != "window" or t_end is None or self._rise_sent is None or t_end > self._rise_sent \
            or lag > 0.5 * (self.target + self.bound)
        self._since_change += source == "window"
        prev = self._prev_lag.get(source)
        change = lag - prev if prev is not None else 0.0  # per stride of sensor time (ticks come once per stride)
        self._prev_lag[source] = lag
        rising = lag > self.target and lag + DRAIN_WINDOWS * change > self.target
        blocked = self.blocked_seconds()
        held = blocked - self._blocked_at.get(source, 0.0) > 0.1 * self.stride / self.speed
        self._blocked_at[source] = blocked
        if self.worker and source == "frontend" and held:
            pass  # the front-end waited for the worker's windows: their lag is the BA's, the window rule acts
        elif self.worker and source == "frontend":
            # the front-end behind on its own core: only its work helps (its packets, then the input), not the BA's
            if lag > self.bound:
                self.fe_level = len(FE_KEEPS) - 1
            elif rising and self.fe_level < len(FE_KEEPS) - 1:
                self.fe_level += 1
            elif rising and prev is not None:
                self.thinning = min(MAX_INPUT_THINNING, 2 * self.thinning)
        elif self.worker and source == "window" and lag > self.target and (self._fe_lag or 0.0) > self.target \
                and not held:
            pass  # the windows wait for a front-end that is behind: a cheaper BA would not bring them sooner
        elif lag > self.bound and self.level < MAX_LEVEL:
            self.level = MAX_LEVEL  # beyond the hard bound: the last level at once
        elif lag > self.target and lag + DRAIN_WINDOWS * change > self.target and self.level < MAX_LEVEL and judged \
                and (source == "frontend" or self._since_change >= DRAIN_WINDOWS or lag > self._lag_at_change):
            self.level += 1
            # heard from the front-end's lag: on to the next level that changes the front-end's work (a level that
            # only degrades the BA cannot help a front-end that is behind)
            while source == "frontend" and self.level < MAX_LEVEL and LEVELS[self.level][0] == LEVELS[old[0]][0]:
                self.level += 1
        elif self.level == MAX_LEVEL and lag > self.target and prev is not None and judged \
                and lag + DRAIN_WINDOWS * change > self.target:
            self.thinning = min(MAX_INPUT_THINNING, 2 * self.thinning)
        elif source == "window" and lag < self.target and lag + DRAIN_WINDOWS * change < self.target \
                and (self._fe_lag or 0.0) < self.target:
            if self.thinning > 1:
                if lag < 0.5 * self.target:
                    self.thinning //= 2
            elif self.worker and self.fe_level > 0:
                if (self._fe_lag or 0.0) < 0.5 * self.target and self._frontend_fits_less_skipped():
                    self.fe_level -= 1
            elif self.level > 0 and self._since_change >= RELAX_WINDOWS:
                cost = self.predicted_cost()
                if cost is not None and cost < self.relax_headroom(lag):
                    self.predicted.append(cost)
                    self.level -= 1
        self.max_thinning = max(self.max_thinning, self.thinning)
        if self.level != old[0]:  # a rise is given time (below); after a fall the next rise is judged afresh
            self._lag_at_change = lag if self.level > old[0] else -math.inf
        if (self.level > old[0] or self.thinning > old[1]) and self.online is not None:
            self._rise_sent = self.online.frontend_until
        if (self.level, self.thinning, self.fe_level) != old:
            self._since_change = 0
            self._costs = []  # costs are measured afresh at the new level
            self.apply()

    def apply(self) -> None:
        """Set OnlineSlam's degradation to the current level and thinning."""
        if self.online is not None:
            self.online.degrade(self.fe_keep(), self.ba_cap(self.level, self._window_events),
                                LEVELS[self.level][2], self.ba_budget(), self.thinning, loop_idle_only=self.level > 0)

    def summary(self) -> dict:
        lags = np.asarray(self.lags) if self.lags else np.zeros(1)
        sensor = sum(self.level_seconds)
        return {
            "windows": len(self.lags),
            "max_lag_s": float(lags.max()), "mean_lag_s": float(lags.mean()),
            "latency_mean_s": float(np.mean(self.latency_mean)) if self.latency_mean else 0.0,
            "latency_max_s": float(np.max(self.latency_max)) if self.latency_max else 0.0,
            "level_sensor_seconds": {str(k): v for k, v in enumerate(self.level_seconds)},
            "degraded_fraction": float(1.0 - self.level_seconds[0] / sensor) if sensor > 0 else 0.0,
            "ba_windows_skipped": self.windows_skipped, "ba_windows_sampled_below_cap": self.windows_sampled,
            "ba_windows_cut_short": self.windows_cut,
            "ba_events_fraction": self.ba_used / self.ba_offline if self.ba_offline else 1.0,
            "input_thinned_sensor_seconds": self.thinned_seconds, "input_max_thinning": self.max_thinning,
            # wall seconds of work per sensor second in the last windows (main process, worker, the BA's and the
            # front-end's parts) and the predicted costs that let the controller relax
            "last_costs": self.mean_costs(), "relax_predicted_costs": self.predicted,
        }


def _worker_threads() -> int | None:
    """Taichi threads of the back-end worker in real time: every core unless a thread count was chosen (None: the
    chosen one). The main process sleeps most of the time (it waits for events to be due), so the back-end, the larger
    cost, can use the other core too. Offline --parallel keeps half the cores each: there both processes are busy,
    and oversubscribed Taichi pools wait."""
    return None if runtime.threads_chosen() else runtime.available_cores()


def _wake_time(first_pending: float, s_now: float, handed_until: float, slice_s: float, t0: float) -> float | None:
    """Sensor time the replay sleeps until before its next hand-over, or None to hand over now: when nothing is due,
    or less than one slice (``realtime_chunk``) of events is due since the last hand-over, it waits for the next
    slice boundary (the loop would otherwise hand over whatever its own few microseconds let through: many tiny
    pushes, each paying a push's fixed cost)."""
    if first_pending <= s_now and s_now >= handed_until + slice_s:
        return None
    k = math.ceil((first_pending - t0) / slice_s)
    return max(t0 + k * slice_s, first_pending, handed_until + slice_s)


def _take_due(pending: Events, s_now: float) -> tuple[Events, Events, float]:
    """(the due events, at most ``HAND_OVER_EVENTS``; the rest; the sensor time handed over). That time is the last
    due event's, not the clock: behind schedule, a hand-over holds only milliseconds of a fast sensor's events, and
    waiting a slice after each one would throttle the replay below the sensor's rate."""
    i = min(int(np.searchsorted(pending.t, s_now, side="right")), HAND_OVER_EVENTS)
    return pending[:i], pending[i:], float(pending.t[i - 1])


def run_realtime(chunks: Iterable[Events], camera: Camera, config: SlamConfig = SlamConfig(), *,
                 backend_process: bool = False, progress_total: float | None = None, log=None):
    """CMax-SLAM on a recording replayed in sensor time (module docstring); returns the SlamResult with a
    "realtime" block in its report. ``chunks``: time-ordered Events chunks (a dataset's ``iter_events``)."""
    from .slam import OnlineSlam

    config = resolve_config(config, camera)
    rt = config.realtime
    speed = float(rt.realtime_speed)
    min_pause = config.frontend.still_span_factor * config.frontend.dt_ang_vel  # W: a longer gap is a pause
    ctl = RealtimeController(config, speed, worker=backend_process)
    be = config.backend
    # with a worker, push() waits while the events sent run more than two windows and a stride ahead of the
    # worker's last window (bounded in sensor time): the front-end then runs while the worker does a window's BA
    worker_threads = _worker_threads() if backend_process else None
    online = OnlineSlam(camera, config, on_window=ctl.on_window, backend_process=backend_process,
                        queue_size=100_000,
                        max_backlog=2 * be.backend_time_window_size + be.backend_sliding_window_stride,
                        loop_slice_seconds=LOOP_SLICE_SHARE * be.backend_sliding_window_stride / speed,
                        worker_threads=worker_threads)
    ctl.online = online
    ctl.apply()  # level 0's BA budget
    idle = {"sleep": 0.0}
    ctl.idle_seconds = lambda: idle["sleep"] + online.backend.blocked_seconds
    ctl.blocked_seconds = lambda: online.backend.blocked_seconds
    online.wait_ready()  # the sensor clock starts once both processes can work
    reader = _prepared_reader(online, chunks)
    pending, eof = Events.empty(), False
    counts = {"read": 0, "handed": 0, "dropped": 0}
    cpu_io = sleep_s = 0.0
    handed_until = -math.inf  # sensor time up to which events were handed over
    cpu0 = time.process_time()
    bar, shown = progress(total=progress_total, desc="slam (real time)", unit="s"), None
    try:
        while True:
            if len(pending) == 0 and not eof:
                tic = time.process_time()
                chunk = next(reader, None)
                cpu_io += time.process_time() - tic
                if chunk is None:
                    eof = True
                else:
                    counts["read"] += len(chunk)
                    # checked and hot-pixel filtered at once (OnlineSlam.screen), handed over when due
                    pending = Events.concatenate(online.screen(chunk))
                continue
            if len(pending) == 0:
                break
            now = time.monotonic()
            if ctl.wall0 is None:
                ctl.wall0, ctl.t0 = now, float(pending.t[0])
                if log is not None:
                    log(f"replaying in sensor time (speed {speed:g}x) from t = {ctl.t0:.6f} s")
            s_now = ctl.t0 + (now - ctl.wall0) * speed
            wake = _wake_time(float(pending.t[0]), s_now, handed_until, rt.realtime_chunk, ctl.t0)
            if wake is not None:
                wait = ctl.due(wake) - now
                if wait > 0:
                    time.sleep(wait)
                    sleep_s += wait
                    idle["sleep"] = sleep_s
                continue
            last = handed_until
            batch, pending, handed_until = _take_due(pending, s_now)
            for _ in _hand_over(online, ctl, batch, last, min_pause, counts):
                if online.frontend_until is not None:
                    bar.update(online.frontend_until - (shown if shown is not None else online.frontend_until))
                    shown = online.frontend_until
        if counts["read"] == 0:
            raise InputError("no events to process")
        result = online.close()
    except BaseException:
        online.abort()
        raise
    finally:
        bar.close()
    counts.update(cpu_io=cpu_io, sleep_s=sleep_s, cpu_total=time.process_time() - cpu0)
    result.report["realtime"] = _realtime_block(online, ctl, result, config, counts, backend_process, worker_threads)
    result.realtime_trace = ctl.trace
    return result


def _prepared_reader(online, chunks: Iterable[Events]) -> Iterator[Events]:
    """The chunks, the first read now (before the replay's clock starts): its event rate prepares the back-end's
    event memory (``OnlineSlam.prepare``)."""
    reader = iter(chunks)
    first = next(reader, None)
    if first is None:
        return reader
    if len(first) > 1:
        online.prepare(len(first) / max(float(first.t[-1] - first.t[0]), 1e-6))
    return itertools.chain([first], reader)


def _hand_over(online, ctl: RealtimeController, batch: Events, last: float, min_pause: float, counts: dict):
    """Push the due events (1 of the controller's q), yielding after each push. The event ending a pause goes in a
    push of its own, recorded with the front-end's progress before it."""
    first = last if last > -math.inf else batch.t[0]
    if batch.t[-1] - first > min_pause:  # a pause may lie inside (a batch is a few ms at high rates: rarely)
        gaps = np.diff(batch.t, prepend=first)
        cuts = np.flatnonzero(gaps > min_pause)
        pause_at = set(cuts.tolist())
    else:
        cuts, pause_at = np.zeros(0, np.int64), set()
    bounds = [0, *cuts[cuts > 0].tolist(), len(batch)]
    for i0, i1 in zip(bounds[:-1], bounds[1:]):
        part = batch[i0:i1]
        if i0 in pause_at:
            ctl.pauses.append((last if i0 == 0 else float(batch.t[i0 - 1]), float(part.t[0]), online.frontend_until))
        q = ctl.thinning
        if q > 1:
            kept = every_qth(part, q, counts["handed"] + counts["dropped"])
            counts["dropped"] += len(part) - len(kept)
            part = kept
        counts["handed"] += len(part)
        if len(part):
            online.push_screened(part)
            ctl.on_frontend(time.monotonic(), online.frontend_until)
            yield


def _realtime_block(online, ctl: RealtimeController, result, config: SlamConfig, counts: dict,
                    backend_process: bool, worker_threads: int | None) -> dict:
    """report.json's "realtime" block."""
    rt, speed = config.realtime, float(config.realtime.realtime_speed)
    read, handed, dropped = counts["read"], counts["handed"], counts["dropped"]
    cpu_io, sleep_s, cpu_total = counts["cpu_io"], counts["sleep_s"], counts["cpu_total"]
    summary = ctl.summary()
    fe_cpu, be_cpu = online.runner.cpu_seconds, online.backend_cpu_seconds
    packets = max(online.packets_seen, 1)
    fe_fraction = 1.0 - online.packets_skipped / packets
    # of the events that passed the hot-pixel filter (screened as read: its drops are no degradation), those not
    # thinned out
    input_fraction = handed / (handed + dropped) if handed + dropped else 1.0
    worker = result.report.get("backend_process")
    other = max(0.0, cpu_total - fe_cpu - (be_cpu if worker is None else 0.0) - cpu_io)
    handover = online.cpu_seconds["handover"]
    report = {
        "speed": speed, "target_lag_s": rt.realtime_target_lag, "max_lag_bound_s": rt.realtime_max_lag,
        "chunk_s": rt.realtime_chunk, "events_read": int(read), "events_handed_over": int(handed),
        # 1 exactly when every event was used as in the offline run (no event dropped, no packet skipped, no window
        # sampled below the configured cap); else the smaller of the stages' fractions times the handed-over one
        "events_used_fraction": input_fraction * min(fe_fraction, summary["ba_events_fraction"]),
        **summary,
        "degradation_applied": bool(summary["degraded_fraction"] > 0 or dropped > 0 or summary["ba_windows_cut_short"]),
        "frontend_packets": int(online.packets_seen), "frontend_packets_skipped": int(online.packets_skipped),
        "input_events_dropped": int(dropped),
        "min_window_events": int(rt.realtime_min_window_events),
        "cpu_seconds": {
            "frontend": fe_cpu, "backend": be_cpu if worker is None else online.backend_cpu_seconds,
            "io": cpu_io,
            # this process: bearings, buffers, slicing, the hand-over to the worker, the controller; of it "ingest"
            # (checks, hot-pixel filter, slicing), "handover" (to the worker: ring writes and messages; in one
            # process: bearings and the window buffer), "close" (the end of the stream: the last packets and windows,
            # the worker's outcome; once per run) and "replay" (the rest: due events, thinning, the controller)
            "other": other,
            "ingest": online.cpu_seconds["ingest"], "handover": handover, "close": online.cpu_seconds["close"],
            "replay": max(0.0, other - online.cpu_seconds["ingest"] - handover - online.cpu_seconds["close"]),
            "main_process": cpu_total,
            **({"backend_process": worker["cpu_seconds"]} if worker is not None else {}),
        },
        # CPU seconds per stage of the back-end (fit, ba, settle, loop) and of its worker's loop (receive: waiting
        # for and unpickling input, events: bearings and the window buffer, send: the window messages)
        "stage_cpu_seconds": {**result.report["backend"]["stages"]["cpu_seconds"],
                              **result.report["backend"].get("worker_stages", {}).get("cpu_seconds", {})},
        "sleep_seconds": sleep_s,
        "wall_seconds": (time.monotonic() - ctl.wall0) if ctl.wall0 is not None else 0.0,
        "threads": {"main_process": runtime.num_threads(),
                    **({"backend_process": worker_threads or runtime.num_threads()} if backend_process else {})},
    }
    return report


def describe(report: dict) -> str:
    """One line for the command's summary."""
    levels = {k: v for k, v in report["level_sensor_seconds"].items() if v > 0 and k != "0"}
    parts = [f"level {k} {v:.1f} s" for k, v in levels.items()]
    for key, what in (("frontend_packets_skipped", "packets skipped"), ("ba_windows_skipped", "BA skipped"),
                      ("ba_windows_cut_short", "BA cut short"), ("input_events_dropped", "events dropped")):
        if report[key]:
            parts.append(f"{report[key]} {what}")
    degr = ", ".join(parts) if report["degradation_applied"] else "none"
    return (f"real time: lag max {report['max_lag_s']:.3f} s, mean {report['mean_lag_s']:.3f} s; latency mean "
            f"{report['latency_mean_s']:.3f} s; events used {report['events_used_fraction']:.3f}; degradation: {degr}")
