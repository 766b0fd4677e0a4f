"""CMax-omega front-end (paper Sec. II-B, III-C1): angular velocity at equispaced times by contrast maximisation.

Data flow: a stream of ``Events`` chunks -> rolling buffer -> one packet per timestamp
t_j = t_first + dt/2 + j dt (dt = ``dt_ang_vel``) -> omega_j maximising the IWE contrast (BFGS or the
reference's Fletcher-Reeves CG, warm-started from omega_{j-1}) -> integrated to a rotation trajectory (R(t_0) = I).

Slicing (``frontend_slicing``):
- ``"paper"``: the N = ``num_events_per_packet`` events centred on t_j; if they span more than
  W = ``still_span_factor * dt_ang_vel`` seconds the camera is declared still (omega = 0). With a
  fixed N this fails when the event rate swings (slow phases give omega = 0 and the trajectory drifts).
- ``"bounded"`` (default): the same N-event packet, but when it spans more than W it is shrunk to the
  events inside the window [t_j - W/2, t_j + W/2]. Still (omega = 0) only when that window holds fewer
  than ``frontend_min_event_rate * W`` events (an event-rate floor: 1000 events per 0.1 s on a DAVIS240C)
  or none at all. No per-sequence tuning of N is needed: slow phases keep a 100 ms window of events.
Both rules clip packets at the ends of the stream. N, the thinning cap below and the rate floor default to
values derived from the sensor's pixel count (``sensor_defaults``: the IWE holds as many events per pixel on a
VGA or HD sensor as the reference's 10 000 on a DAVIS240C). ``frontend_event_sample_rate`` Q keeps 1 event of Q
(systematic, over the whole stream) before slicing.

Speed (bounded cost per packet at any event rate): a packet holding more than
``frontend_max_packet_events`` events (e.g. every event of the minimum span at a few Mev/s) is thinned to
1 of k events before the optimisation; its span, hence the motion that makes omega measurable, is kept.
The optimiser starts from the linear prediction 2 omega_{j-1} - omega_{j-2} (``frontend_warm_start``), usually a
fraction of a pixel from the optimum. ``frontend_optimizer="bfgs"`` (default) keeps the BFGS inverse Hessian of
the last packet (the scaled cost below changes little from packet to packet), so the first step is a
quasi-Newton one; it stops once its next step would move the farthest event by less than
``frontend_bfgs_step_tol`` (0.05 px): about 2.2 evaluations per packet. ``"cg"`` is the reference's Fletcher-Reeves CG with the
"secant" first trial step and a loose line search (tolerance 0.5, at most 4 evaluations): 4-5 evaluations per
packet instead of 13-16 with the reference's strict line search, for the same accuracy
(pipelines/evaluation/bench_frontend.py).

Pixel grid (``frontend_pixel_dither``): integer event pixels are dithered by up to half a pixel (``PixelDither``), or
the contrast favours omega = 0 whenever a packet's motion is below about a pixel (starts, slow phases).

Suspect and flat packets: after the optimisation of 1 of ``frontend_gain_check_every`` (10) moving packets the
contrast at omega = 0 is evaluated once more (cost only: vote and blur, ~0.6 of an evaluation; on 1 of 4 packets it
cost ~6 % of the front-end); a solution that moves the packet's farthest event by >= 1 px but raises the contrast by
less than ``frontend_min_contrast_gain`` is flagged (the events do not constrain omega: e.g. packets far too small
for the sensor). Most checked packets suspect: the run's status is "suspect" instead of "ok". Unchecked packets have
gain nan and are never suspect. Without the grid's pull an optimiser on a flat cost stops anywhere, so
(``frontend_flat_is_still``) a slow packet (optimum under 1 px), a packet whose optimum lies >= 1 px from its warm
start, or a suspect one is flat unless its events measure a motion: the score test of omega = 0
(``AngularVelocityEstimator.motion_score``, ``frontend_min_motion_score``); a flat packet takes omega = 0.

Lookbacks (``frontend_flat_lookback``, ``FrontendRunner._past_motion``): a flat packet's recent past (the last 4x,
16x, ... its span) is score-tested too, so a motion too slow for one packet still counts as one for the back-end
(which refines only windows that moved: ``backend_skip_still_windows``), and a packet that measures a motion right
after a flat one keeps it only if its lookback measures it too (a noise packet passing the test by chance).

Scaling (so that the reference's tolerances mean the same across packet sizes and resolutions): the
optimiser sees x = omega * s with s = f * max_k |dt_k| (f: mean focal length), i.e. x is roughly the
displacement in pixels of the packet's farthest-in-time event, and the cost C / mu0^2 with
mu0 = n / (width * height), the mean IWE value of a packet of n events: the variance becomes the squared
coefficient of variation of the IWE, dimensionless and independent of n and of the sensor size.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Iterable, Iterator

import numpy as np

from ti_cmax import so3
from ti_cmax.camera import Camera
from ti_cmax.config import SLICING_RULES, FrontendConfig, config_to_dict
from ti_cmax.errors import InputError
from ti_cmax.events import Events
from ti_cmax.kernels.iwe import IWEWorkspace
from ti_cmax.trajectory import Trajectory

from .optim import bfgs, fletcher_reeves
from .sensor_defaults import resolve_frontend


NO_MOTION_MEASURABLE = ("the events span no time (no events, or all at one timestamp): no packet, so no angular "
                        "velocity, can be estimated")


@dataclass(frozen=True, eq=False)
class FrontendResult:
    """Angular velocity per packet and what happened in each packet."""

    t: np.ndarray  # (M,) packet timestamps t_j (s)
    omega: np.ndarray  # (M, 3) rad/s, camera frame
    num_events: np.ndarray  # (M,) events in the packet (0 when still/empty)
    span: np.ndarray  # (M,) time span of the selected packet (s)
    iterations: np.ndarray  # (M,) CG line searches
    evaluations: np.ndarray  # (M,) contrast+gradient evaluations
    still: np.ndarray  # (M,) bool, omega set to 0 by the still-camera rule
    cost: np.ndarray  # (M,) normalised contrast at the solution (nan when still)
    gain: np.ndarray  # (M,) contrast at the solution over the contrast at omega = 0 (nan when still or unchecked)
    suspect: np.ndarray  # (M,) bool: the solution moves events by >= 1 px but barely sharpens the IWE
    flat: np.ndarray = None  # (M,) bool: omega set to 0, the motion not significant (score test, estimate())
    # (M,) span (s) of the lookback that measured a motion around a flat packet (FrontendRunner; 0: none)
    lookback: np.ndarray = None
    timing: dict = field(default_factory=dict)  # compile_seconds, wall_seconds, us_per_event, ...
    config: FrontendConfig = field(default_factory=FrontendConfig)

    def __len__(self) -> int:
        return len(self.t)

    @property
    def status(self) -> str:
        """"suspect" when the front-end's counters say omega cannot be trusted (ti_cmax.status: most checked packets
        suspect, too few events, most packets zero at a high event rate), else "ok"."""
        from ti_cmax.status import run_status

        return run_status({"frontend": self.summary()})[0]

    @property
    def checked(self) -> np.ndarray:
        """(M,) bool: moving packets whose contrast gain over omega = 0 was evaluated (the suspect check)."""
        return ~self.still & ~np.isnan(self.gain)

    def trajectory(self) -> Trajectory:
        """Integrate omega (midpoint rule on SO(3)) to R_world_from_camera at the packet times, R(t_0) = I."""
        if len(self.t) == 0:
            raise InputError(NO_MOTION_MEASURABLE)
        return Trajectory(self.t, so3.integrate_angular_velocity(self.t, self.omega))

    def _trust_counters(self) -> dict:
        """What ti_cmax.status reads to say whether omega can be trusted: packets holding fewer events than the still
        rule's floor (``frontend_min_event_rate`` x W: at the stream's ends, or a tiny input; omega then is noise, 40
        rad/s off on 100 events), and the median event rate (events / span) of the packets that moved and of those
        set to omega = 0 by the flat test (a still camera sees noise, far below the rate of a moving one)."""
        cfg = self.config
        floor = int(np.ceil(cfg.frontend_min_event_rate * cfg.still_span_factor * cfg.dt_ang_vel))
        flat = self.flat if self.flat is not None else np.zeros(len(self.t), bool)
        moving, zero = ~self.still & ~flat, ~self.still & flat
        rate = self.num_events / np.maximum(self.span, 1e-9)
        return {
            "min_packet_events": floor,
            "small_packets": int(np.count_nonzero(~self.still & (self.num_events < floor))) if floor > 0 else 0,
            "event_rate": {"moving": float(np.median(rate[moving])) if np.any(moving) else None,
                           "flat": float(np.median(rate[zero])) if np.any(zero) else None,
                           "floor": float(cfg.frontend_min_event_rate)},
        }

    def summary(self) -> dict:
        """JSON-friendly summary (for report.json)."""
        return {
            "packets": int(len(self.t)),
            "still_packets": int(np.count_nonzero(self.still)),
            "suspect_packets": int(np.count_nonzero(self.suspect)),
            "flat_packets": int(np.count_nonzero(self.flat)) if self.flat is not None else 0,
            "lookback_packets": int(np.count_nonzero(self.lookback)) if self.lookback is not None else 0,
            "checked_packets": int(np.count_nonzero(self.checked)),
            "median_contrast_gain": float(np.nanmedian(self.gain)) if np.any(~self.still) else 0.0,
            "mean_iterations": float(np.mean(self.iterations)) if len(self.t) else 0.0,
            "mean_evaluations": float(np.mean(self.evaluations)) if len(self.t) else 0.0,
            "mean_packet_events": float(np.mean(self.num_events[~self.still])) if np.any(~self.still) else 0.0,
            **self._trust_counters(),
            **{k: (float(v) if isinstance(v, (int, float, np.floating, np.integer)) else v)
               for k, v in self.timing.items()},
        }


# ------------------------------------------------------------------------------------------------
# streaming and slicing
# ------------------------------------------------------------------------------------------------

CHUNK_EVENTS = 1_000_000


def as_chunks(events_or_chunks, chunk_size: int = CHUNK_EVENTS) -> Iterator[Events]:
    """Time-ordered ``Events`` chunks from an ``Events`` object (split into views of ``chunk_size`` events, so
    per-chunk work such as bearings stays bounded), an iterable of chunks, or a dataset with ``iter_events()``."""
    if isinstance(events_or_chunks, Events):
        for i in range(0, len(events_or_chunks), chunk_size):
            yield events_or_chunks[i:i + chunk_size]
        return
    if hasattr(events_or_chunks, "iter_events"):
        events_or_chunks = events_or_chunks.iter_events()
    for chunk in events_or_chunks:
        if not isinstance(chunk, Events):
            raise InputError(f"expected Events chunks, got {type(chunk).__name__}")
        yield chunk


def every_qth(chunk: Events, q: int, offset: int) -> Events:
    """The events of ``chunk`` whose global index (``offset`` = index of its first event) is a multiple of q."""
    return chunk[(-offset) % q::q] if q > 1 else chunk


def downsampled(chunks: Iterable[Events], q: int) -> Iterator[Events]:
    """Keep events whose global index is a multiple of q (same as Events.downsample on the whole stream)."""
    offset = 0
    for chunk in chunks:
        n = len(chunk)
        chunk = every_qth(chunk, q, offset)
        offset += n
        if len(chunk):
            yield chunk


def fixed_count_packets(chunks: Iterable[Events], n: int) -> Iterator[Events]:
    """Consecutive packets of exactly ``n`` events from time-ordered chunks (a last remainder below n is dropped)."""
    pending: list[Events] = []
    count = 0
    for chunk in chunks:
        i = 0
        while i < len(chunk):
            take = min(n - count, len(chunk) - i)
            pending.append(chunk[i:i + take])
            count += take
            i += take
            if count == n:
                yield pending[0] if len(pending) == 1 else Events.concatenate(pending)
                pending, count = [], 0


def time_intervals(chunks: Iterable[Events], length: float) -> Iterator[tuple[int, float, Events]]:
    """(k, t_start_k, events of [t0 + k length, t0 + (k + 1) length)) for k = 0, 1, ..., t0 the first event's time;
    empty intervals included. Events exactly at the end of the last interval belong to it (as with
    ceil((t_last - t0) / length) intervals over the whole stream)."""
    buf = None
    t0 = None
    k = 0
    for chunk in chunks:
        if len(chunk) == 0:
            continue
        if buf is None:
            t0, buf = float(chunk.t[0]), chunk
        else:
            buf = Events.concatenate([buf, chunk])
        while buf.t[-1] > t0 + length * (k + 1):
            i = int(np.searchsorted(buf.t, t0 + length * (k + 1), side="left"))
            yield k, t0 + length * k, buf[:i]
            buf = buf[i:]
            k += 1
    if buf is not None:
        yield k, t0 + length * k, buf


@dataclass(frozen=True)
class Packet:
    t_ref: float
    events: Events  # the selected events (empty when still)
    span: float
    still: bool


class PacketSlicer:
    """Rolling-buffer slicer: one :class:`Packet` per equispaced timestamp (see module docstring).

    Push form (for live sources): ``push(chunk)`` yields the packets the chunk completes, ``flush()`` the rest once
    the stream has ended; ``slicer(chunks)`` does both over an iterable. A packet is emitted as soon as later events
    cannot change it, so the packets do not depend on how the stream is chunked.

    Memory: the buffer holds the events from the current packet's start to at most N/2 events or W/2
    seconds past its centre, plus the chunk being read.
    """

    def __init__(self, config: FrontendConfig):
        """``config`` must be resolved for the camera (``sensor_defaults.resolve_frontend``): no derived 0s."""
        if config.num_events_per_packet <= 0 or config.frontend_min_event_rate <= 0:
            raise ValueError("the slicer needs a front-end config resolved for the camera (resolve_frontend)")
        self.n = int(config.num_events_per_packet)
        self.dt = float(config.dt_ang_vel)
        self.window = float(config.still_span_factor) * self.dt
        self.rule = config.frontend_slicing
        self.min_events = max(1, int(np.ceil(config.frontend_min_event_rate * self.window)))
        self.min_span = float(config.frontend_min_packet_span)
        self.events_read = 0
        self._buf = Events.empty()
        self._pending: list[Events] = []  # chunks pushed since the buffer was last joined (joined when a packet may be due)
        self._t_last = -np.inf
        self.t_ref: float | None = None  # the next packet's centre (None before the first event)
        self.packets_emitted = 0

    def __call__(self, chunks: Iterable[Events]) -> Iterator[Packet]:
        for chunk in chunks:
            yield from self.push(chunk)
        yield from self.flush()

    def push(self, chunk: Events) -> Iterator[Packet]:
        """Append a time-ordered chunk; yield every packet it completes."""
        if len(chunk) == 0:
            return
        if chunk.t[0] < self._t_last:
            raise InputError(f"event chunks are not in time order (t={float(chunk.t[0])!r} after {self._t_last!r})")
        self._t_last = float(chunk.t[-1])
        self.events_read += len(chunk)
        self._pending.append(chunk)
        if self.t_ref is None:
            self.t_ref = float(chunk.t[0]) + 0.5 * self.dt
        # the buffer is joined only when a packet may be final (a live source pushes ~2 ms chunks: joining on
        # every push copied the whole buffer each time); _known() on the parts equals it on the joined buffer
        if not self._known():
            return
        self._join()
        while self._known():
            yield self._emit()

    def flush(self) -> Iterator[Packet]:
        """The stream has ended: yield the packets up to the last event (clipped at the end). A stream shorter than
        half a step (dt_ang_vel / 2, where the first packet is centred) still gets one packet, centred on its last
        event, if it spans any time at all."""
        self._join()
        if not self.packets_emitted and len(self._buf) and self._buf.t[0] < self._buf.t[-1] < self.t_ref:
            self.t_ref = float(self._buf.t[-1])
        while self.t_ref is not None and len(self._buf) and self.t_ref <= self._buf.t[-1]:
            yield self._emit()

    def _join(self) -> None:
        if self._pending:
            self._buf = Events.concatenate([self._buf, *self._pending])
            self._pending = []

    def _known(self) -> bool:
        """The packet around t_ref is final: N - N/2 events from the centre on, or events later than t_ref + W
        (then the full packet would span more than W anyway). Counts over the buffer and the pending chunks."""
        t_ref = self.t_ref
        parts = [self._buf, *self._pending]
        if t_ref is None or not any(len(e) for e in parts):
            return False
        t_last = self._t_last
        if t_last > t_ref + self.window:
            return True
        if t_last < t_ref + 0.5 * self.min_span:
            return False
        after = sum(len(e) - int(e.index_at(t_ref)) for e in parts)  # events at or after the centre
        return after >= self.n - self.n // 2

    def _emit(self) -> Packet:
        buf, t_ref, half = self._buf, self.t_ref, self.n // 2
        c = int(buf.index_at(t_ref))
        i0, i1 = max(0, c - half), min(len(buf), c + self.n - half)
        if self.min_span > 0:  # high event rates: take every event of the minimum span
            i0 = min(i0, int(buf.index_at(t_ref - 0.5 * self.min_span)))
            i1 = max(i1, int(buf.index_at(t_ref + 0.5 * self.min_span)))
        packet = buf[i0:i1]
        span = packet.duration
        still = False
        if span > self.window:
            if self.rule == "paper":
                still = True
            else:
                j0 = max(i0, int(buf.index_at(t_ref - 0.5 * self.window)))
                j1 = min(i1, int(buf.index_at(t_ref + 0.5 * self.window, side="right")))
                packet = buf[j0:j1]
                span = packet.duration
                still = len(packet) < self.min_events
        if len(packet) < 2 or packet.duration <= 0:
            still = True
        # drop what no later packet can use: the next packet starts at or after index c_next - N/2
        self.t_ref = t_ref + self.dt
        drop = max(0, min(int(buf.index_at(self.t_ref)) - half, int(buf.index_at(self.t_ref - 0.5 * self.min_span))))
        if drop > 0:
            self._buf = buf[drop:]
        self.packets_emitted += 1
        return Packet(t_ref, Events.empty() if still else packet, span, still)


DITHER_PERIOD = 1 << 16  # distinct offsets of the dither table (a packet's start in it: a hash of its time)


class PixelDither:
    """Sub-pixel dither of a packet's integer event pixels, as offsets of its bearings (x / fx, y / fy on the unit
    depth plane): up to ``amplitude`` px, uniform, independent per event (a fixed table of uniform draws, read from an
    offset that a packet's time picks: no per-event hashing, one add per coordinate; deterministic for a packet
    sequence, whatever the chunking).

    Why: event coordinates are integers, so at omega = 0 every event sits on a pixel centre and its bilinear vote is
    one pixel, while any motion spreads the votes over four: the contrast favours omega = 0 by a margin that does not
    depend on the motion (a pixel-grid bias of CMax). When a packet's motion is below ~1 px (a camera starting or
    slowing down, slow star-tracker pans) the bias wins and omega is pulled to 0 (measured on a VGA pan starting from
    rest with 1 Hz/px noise: omega exactly 0 for the first 0.24 s, then lagging by 0.02 rad/s; on a synthetic 1 px
    motion the error is 0.05-0.11 rad/s on integer pixels, 0.005-0.008 dithered). Dithering each event by up to half
    a pixel (uniform over the pixel) takes the grid out of the IWE."""

    def __init__(self, camera: Camera, amplitude: float, dtype, size: int = 0):
        self.amplitude, self.dtype = float(amplitude), np.dtype(dtype)
        self.fx, self.fy = camera.fx, camera.fy
        self._grow(max(int(size), 1))

    def _grow(self, size: int) -> None:
        rng = np.random.default_rng(20261203)
        u = rng.uniform(-self.amplitude, self.amplitude, (DITHER_PERIOD + size, 2)).T
        # one table per column: adding a contiguous column is ~10x faster than adding an (n, 2) block to the
        # strided view of the packet's first two columns (0.4 ms per 20 000 events, numpy's inner loop of 2)
        self._x = (u[0] / self.fx).astype(self.dtype)
        self._y = (u[1] / self.fy).astype(self.dtype)

    def apply(self, packed: np.ndarray, n: int, t_ref: float) -> None:
        """Add the dither to the bearings' x, y (columns 0, 1) of the first n rows of ``packed``, in place."""
        if n > len(self._x) - DITHER_PERIOD:
            self._grow(n)
        offset = (int(round(t_ref * 1e5)) * 40503) % DITHER_PERIOD
        packed[:n, 0] += self._x[offset:offset + n]
        packed[:n, 1] += self._y[offset:offset + n]


class Lookback:
    """The recent events of the stream, for testing a flat packet's past for motion over a longer span
    (``FrontendRunner``).

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


# ------------------------------------------------------------------------------------------------
# per-packet estimation
# ------------------------------------------------------------------------------------------------

# the score test (AngularVelocityEstimator.motion_score) runs where a packet's optimum moves its farthest event by
# under this many pixels (besides jumps from the warm start and suspects): the flat packets found on simulated pans
# moved 0.1-0.9 px but for jumps; 2 px found the same flats (bay 14 s, city 1 M ev/s) with 1.7-1.8x the evaluations at
# omega = 0 (measured with an earlier noise estimate: 8 sub-packets)
SLOW_PX = 1.0
# ... and where the optimum lies at least 1 px and this fraction of its own motion from the warm start: an optimiser
# wandering on a flat cost lands anywhere (its jump is about its own size), a fast motion's packets move by 50-200 px
# and a 1 px jump is a 1 % change of omega; testing those at omega = 0, where the IWE is blurred flat over the whole
# motion, declared 40 of 49 packets of a 20 rad/s DAVIS240C pan flat (front-end alone 105 deg; 2.0 with the fraction;
# the paper suite, the bay / street / town / DVS128 pans: the same tests, bitwise the same)
JUMP_FRACTION = 0.25
# a packet that fails the score test although its optimum moves events by FAST_PX or more is tested again over the
# sub-span in which that motion is SUB_PX (AngularVelocityEstimator._fast_motion; at least SUB_MIN_EVENTS events):
# never reached on the paper suite and the noisy pans above (their flat packets move under 20 px)
FAST_PX, SUB_PX, SUB_MIN_EVENTS = 20.0, 4.0, 500
# the carried BFGS inverse Hessian is dropped above this condition number (optim.bfgs max_condition): measured on
# six sequences at 1 and 1 of 4 packets, at most 290 (99 % under 145); a collapsed one read 2e4-4e4 and held the
# front-end 0.1 rad/s off a rotation for a second (a 14 s pan at real-time level 4: abs 4.9 deg instead of ~0.5)
BFGS_MAX_CONDITION = 1e3
# lookbacks (frontend_flat_lookback) span 4x, 16x, ... the packet's span; in a run of flat packets one packet of
# LOOKBACK_EVERY looks back (lookbacks of >= 0.16 s change little over 4 packets, 40 ms), the others take its answer
LOOKBACK_FACTOR = 4.0
LOOKBACK_EVERY = 4


class AngularVelocityEstimator:
    """Estimates omega for one packet at a time (keeps the compiled workspace and the warm start)."""

    def __init__(self, camera: Camera, config: FrontendConfig = FrontendConfig(), dtype=np.float32):
        config = resolve_frontend(config, camera)
        self.camera, self.config = camera, config
        self.K = camera.K
        self.focal = 0.5 * (camera.fx + camera.fy)
        cap = config.num_events_per_packet
        if config.frontend_max_packet_events > 0:
            cap = max(cap, config.frontend_max_packet_events)
        self.ws = IWEWorkspace(camera.width, camera.height, dtype, config.frontend_blur_sigma,
                               capacity=cap)
        # integer pixels are dithered (PixelDither: the pixel grid's bias towards omega = 0); float ones are not
        self.dither = PixelDither(camera, config.frontend_pixel_dither, dtype, cap) \
            if config.frontend_pixel_dither > 0 else None
        self.omega = np.zeros(3)
        self.omega_prev = None  # omega of the packet before the last one (linear warm start)
        self.inv_hessian = None  # BFGS: carried from packet to packet (x = pixels of motion, cost normalised)
        self.events_evaluated = 0  # events actually used in the optimisation (after thinning)
        self.event_evaluations = 0  # sum over packets of events used x evaluations (for the cost per event-evaluation)
        self.packets_estimated = 0  # moving packets so far (the suspect check runs on 1 of frontend_gain_check_every)
        self.flat_packets = 0  # packets whose omega was set to 0 by the flat rule (estimate())
        self.checks = 0  # evaluations at omega = 0 (cost only unless score-tested)
        self.score_tests = 0  # packets score-tested (motion_score)
        self.last_gain, self.last_suspect, self.last_flat = np.nan, False, False

    def reset(self) -> None:
        """Forget the warm start (after a still or flat packet)."""
        self.omega = np.zeros(3)
        self.omega_prev = None

    def thin(self, events: Events) -> Events:
        """Keep 1 of k events (k = ceil(n / frontend_max_packet_events)) so a packet holds at most that many;
        uniform in the event index, so the span and the event density pattern are kept."""
        cap = int(self.config.frontend_max_packet_events)
        n = len(events)
        if cap <= 0 or n <= cap:
            return events
        k = -(-n // cap)
        return events[(k // 2)::k]

    def warm_start(self) -> np.ndarray:
        if self.config.frontend_warm_start == "linear" and self.omega_prev is not None:
            return 2.0 * self.omega - self.omega_prev
        return self.omega

    def compile(self) -> float:
        """Compile (or load from the offline cache) the kernels; returns seconds spent."""
        t0 = time.perf_counter()
        self.ws.compile()
        return time.perf_counter() - t0

    def _objective(self, events: Events, t_ref: float):
        """Load a packet (thinned); returns (fun, s): fun(x) = normalised contrast and gradient at omega = x / s,
        s = focal * max |t - t_ref| (pixels per rad/s, so CG steps are in pixels of motion blur)."""
        events = self.thin(events)
        self.events_evaluated += len(events)
        packed = self.camera.bearings(events.x, events.y, dtype=self.ws.dtype, columns=4)
        if self.dither is not None and len(events) and np.issubdtype(events.x.dtype, np.integer):
            self.dither.apply(packed, len(events), t_ref)
        dts = packed[:, 3]
        np.subtract(events.t, t_ref, out=dts, casting="unsafe")
        self.ws.set_packed(packed)
        n = len(events)
        s = self.focal * float(np.max(np.abs(dts))) if n else 0.0
        if not s > 0:
            raise InputError("packet has no time extent")
        mu0 = n / float(self.camera.width * self.camera.height)
        scale = self._scale = 1.0 / (mu0 * mu0)
        measure = self.config.contrast_measure

        def fun(x):
            c, g, _ = self.ws.evaluate(x / s, self.K, measure)
            return c * scale, g * (scale / s)

        return fun, s, n

    def _maximize(self, fun, x0):
        cfg = self.config
        if cfg.frontend_optimizer == "bfgs":
            res, self.inv_hessian = bfgs(
                fun, x0, maximize=True, inv_hessian=self.inv_hessian, init_step=cfg.frontend_cg_init_step,
                max_iter=cfg.frontend_cg_max_iters, grad_tol=cfg.frontend_cg_grad_tol,
                rel_cost_tol=cfg.frontend_cg_rel_cost_tol, max_step=cfg.frontend_bfgs_max_step,
                max_line_evals=cfg.frontend_cg_max_line_evals, step_tol=cfg.frontend_bfgs_step_tol,
                max_condition=BFGS_MAX_CONDITION)
            return res
        return fletcher_reeves(
            fun, x0, maximize=True, init_step=cfg.frontend_cg_init_step,
            line_search_tol=cfg.frontend_cg_line_search_tol, max_iter=cfg.frontend_cg_max_iters,
            grad_tol=cfg.frontend_cg_grad_tol, rel_cost_tol=cfg.frontend_cg_rel_cost_tol,
            max_line_evals=cfg.frontend_cg_max_line_evals, step_guess=cfg.frontend_cg_step_guess,
        )

    def estimate(self, events: Events, t_ref: float, omega0=None):
        """Maximise the normalised contrast for one packet; returns (omega, CGResult, normalised cost).

        The contrast at omega = 0 is evaluated (cost only) on 1 of ``frontend_gain_check_every`` packets (the
        suspect check: gain of the optimum over omega = 0, for the run's status). With ``frontend_flat_is_still``,
        a packet whose optimum moves its farthest event by under SLOW_PX, or lies 1 px and JUMP_FRACTION of its motion
        or more from the warm start (which a smooth motion seldom does while an optimiser wandering on a flat cost does
        at every packet), or a suspect one, is score-tested (:meth:`motion_score`): under
        ``frontend_min_motion_score`` its events do not measure any motion (under a pixel over the packet against the
        noise, or a noise-only IWE) and its optimum is noise, so it is flat: omega = 0 and the warm start is reset;
        unless its optimum moves events by FAST_PX or more and the test passes over a sub-span
        (:meth:`_fast_motion`)."""
        cfg = self.config
        fun, s, n = self._objective(events, t_ref)
        w0 = self.warm_start() if omega0 is None else np.asarray(omega0, float)
        res = self._maximize(fun, w0 * s)
        self.omega_prev, self.omega = self.omega, res.x / s
        scheduled = self.packets_estimated % int(cfg.frontend_gain_check_every) == 0
        # x is the displacement in pixels of the packet's farthest-in-time event
        moved = float(np.linalg.norm(res.x))
        jump = float(np.linalg.norm(res.x - w0 * s))
        tested = cfg.frontend_flat_is_still and (moved < SLOW_PX or jump >= max(1.0, JUMP_FRACTION * moved))
        self.packets_estimated += 1
        self.last_gain, self.last_suspect, self.last_flat = np.nan, False, False
        extra = 0  # evaluations (in packets' worth of events) beyond the optimiser's
        g_zero = None
        if scheduled or tested:
            # how much the solution sharpens the IWE compared with no motion (with the gradient: the score test's)
            c_zero, g_zero, _ = self.ws.evaluate(np.zeros(3), self.K, cfg.contrast_measure, with_grad=tested)
            self.checks += 1
            extra += 1
            c_zero *= self._scale
            gain = float(res.fun / c_zero) if c_zero > 0 else np.inf
            if scheduled:  # the run's status counts the scheduled checks only (an even sample of the packets)
                self.last_gain = gain
                # a motion of >= 1 px that gains less than frontend_min_contrast_gain is not seen in the events
                self.last_suspect = bool(moved >= 1.0 and gain < 1.0 + cfg.frontend_min_contrast_gain)
                if self.last_suspect and cfg.frontend_flat_is_still and not tested:
                    tested = True
                    g_zero = self.ws.evaluate(np.zeros(3), self.K, cfg.contrast_measure)[1]
                    self.checks += 1
                    extra += 1
        if tested and not self._significant(g_zero) and not self._fast_motion(events, t_ref, moved):
            self.declare_flat()
        self.event_evaluations += n * (res.evaluations + extra)
        return self.omega.copy(), res, res.fun

    def measures_motion(self, events: Events, t_ref: float) -> bool:
        """Whether ``events`` (a longer span ending with a flat packet: ``FrontendRunner``'s lookback) measure any
        motion: the score test of omega = 0 over them (one evaluation)."""
        n = self._objective(events, t_ref)[2]
        g_zero = self.ws.evaluate(np.zeros(3), self.K, self.config.contrast_measure)[1]
        self.checks += 1
        self.event_evaluations += n
        return self._significant(g_zero)

    def _fast_motion(self, events: Events, t_ref: float, moved: float) -> bool:
        """A packet whose optimum moves its events by FAST_PX or more and fails the score test: is it a fast motion
        the test cannot see? At omega = 0 such a packet's IWE is blurred over the whole motion (160 px for 40 ms of a
        20 rad/s pan on a DAVIS240C), flat, and its gradient is noise; over the sub-span in which the optimum moves
        events by SUB_PX the blur is small again and the same test has its power (at least SUB_MIN_EVENTS events).
        Without it a stream starting at such speeds (no warm start) had every packet flat: a 0.12 s pan ramping to 40
        rad/s, 11 of 12."""
        if moved < FAST_PX:
            return False
        half = float(np.max(np.abs(events.t - t_ref))) * SUB_PX / moved
        sub = events.slice_time(t_ref - half, t_ref + half)
        return len(sub) >= SUB_MIN_EVENTS and self.measures_motion(sub, t_ref)

    def _significant(self, g_zero) -> bool:
        """The score test of omega = 0 on the loaded events (:meth:`motion_score`) passes: they measure a motion."""
        self.score_tests += 1
        return self.motion_score(g_zero) >= self.config.frontend_min_motion_score

    def declare_flat(self) -> None:
        """The last packet is flat: omega = 0 and the warm start reset (``estimate``'s score test, or
        ``FrontendRunner``: its motion is not confirmed over a longer span)."""
        if not self.last_flat:
            self.last_flat = True
            self.flat_packets += 1
            self.reset()

    def motion_score(self, g_zero) -> float:
        """Score statistic of omega = 0 for the loaded packet: g0^T S^-1 g0, with g0 its contrast gradient at
        omega = 0 (the workspace's last evaluation) and S the noise covariance of g0 estimated from the spread of
        its per-event terms (``IWEWorkspace.gradient_covariance``). Where the events measure no motion it is about
        chi-square with 3 degrees of freedom (synthetic 0.1 s packets, 6 seeds each: still scene with 10 000 noise
        events mean 4.5, 20 000 scene events 1.1, noise alone 2.9; at the true omega of half- and third-pixel
        motions 1.9-3.1), so ``frontend_min_motion_score`` = 16.3 lets 0.1 % of motionless packets through; half a
        pixel of motion scores 170-210 with 5 000 scene events among 10 000 noise events, 11-36 with 2 000."""
        g = np.asarray(g_zero, float)
        cov = self.ws.gradient_covariance()
        if not np.all(np.isfinite(cov)):
            return np.inf  # too few events to tell: keep the optimum, as without the test
        try:
            return float(g @ np.linalg.solve(cov, g))
        except np.linalg.LinAlgError:  # no spread at all (no event in the image at omega = 0): nothing measured
            return 0.0 if not np.any(g) else np.inf

    def contrast_ratio(self, events: Events, t_ref: float, omega) -> tuple[float, np.ndarray]:
        """How well ``omega`` (another method's angular velocity) explains one packet: its contrast over the best
        contrast CG finds from the better of ``omega`` and the warm start (1: a local optimum; well below 1: the
        events say the motion differs). Returns (ratio, best omega); the best becomes the warm start."""
        fun, s, n = self._objective(events, t_ref)
        omega = np.asarray(omega, float)
        given = fun(omega * s)[0]
        warm = self.warm_start()
        x0 = omega * s if given >= fun(warm * s)[0] else warm * s
        res = self._maximize(fun, x0)
        self.event_evaluations += n * (res.evaluations + 2)
        best_c, best_x = (res.fun, res.x) if res.fun > given else (given, omega * s)
        self.omega_prev, self.omega = self.omega, best_x / s
        return (float(max(given, 0.0) / best_c) if best_c > 0 else 1.0), self.omega.copy()


class FrontendRunner:
    """Runs the front-end packet by packet and collects its rows; shared by the front-end alone and SLAM.

    ``slicer(chunks)`` yields packets, ``process(packet)`` returns omega (0 when still) and records the row,
    ``result()`` assembles the :class:`FrontendResult` with timing (compile time apart from steady state).
    """

    def __init__(self, camera: Camera, config: FrontendConfig = FrontendConfig(), dtype=np.float32):
        config = resolve_frontend(config, camera)
        self.config = config
        self.estimator = AngularVelocityEstimator(camera, config, dtype)
        self.slicer = PacketSlicer(config)
        self.width, self.height = camera.width, camera.height
        self._t_checked: float | None = None  # the last event time check() saw
        self.lookback = None
        if config.frontend_flat_lookback > 0 and config.frontend_flat_is_still:
            # the shortest lookback (LOOKBACK_FACTOR x the minimum span) may hold a full packet cap of events
            cap = max(config.num_events_per_packet, config.frontend_max_packet_events)
            base = max(config.frontend_min_packet_span, config.dt_ang_vel)
            self.lookback = Lookback(config.frontend_flat_lookback, cap / (LOOKBACK_FACTOR * base))
        self._flat_run = 0  # flat packets in a row
        self._last_look = 0.0  # span of the run's last lookback that measured a motion (0: none)
        self.rows: list[tuple] = []
        self.last_moving = False  # the last packet measured a motion (itself, or a lookback around it)
        self.events_processed = 0  # events in non-still packets (each counted once per packet): packet_events
        self.input_events = 0  # counted by counted(); 0: the slicer's count is the input
        self.compile_seconds = 0.0
        self.seconds = 0.0  # steady-state time spent in process()
        self.cpu_seconds = 0.0  # CPU time of the process (all threads) spent in process()

    @property
    def events_read(self) -> int:
        return self.slicer.events_read

    def counted(self, chunks: Iterable[Events]) -> Iterator[Events]:
        """The input chunks, checked (``check``) and counted before any event sampling (the unit of us_per_event:
        input events)."""
        for chunk in chunks:
            self.check(chunk)
            self.input_events += len(chunk)
            yield chunk

    def check(self, chunk: Events) -> None:
        """Raise one InputError on events the pipelines cannot take: non-finite or decreasing timestamps (also
        against the previous chunk), integer pixels off the sensor, or a pause longer than ``max_event_gap`` (a
        stray event or a clock jump: bridging it would take ~0.04 s per second of pause). The readers check files
        already; this guards the Python API (2 ns per event)."""
        if len(chunk) == 0:
            return
        if chunk.has_subpixel_coordinates:  # undistorted coordinates (star tracking) may fall off the sensor
            chunk.validate(source="events")
        else:
            chunk.validate(self.width, self.height, source="events")
        t = chunk.t
        if self._t_checked is not None and t[0] < self._t_checked:
            raise InputError(f"event chunks are not in time order (t={float(t[0])!r} after {self._t_checked!r})")
        gaps = np.diff(t)
        k = int(np.argmax(gaps)) if len(gaps) else -1
        gap, at = (float(gaps[k]), float(t[k])) if k >= 0 else (0.0, 0.0)
        if self._t_checked is not None and t[0] - self._t_checked > gap:
            gap, at = float(t[0] - self._t_checked), self._t_checked
        if gap > self.config.max_event_gap:
            raise InputError(f"no events for {gap:.6g} s after t={at!r}: a stray event or a jump of the clock? "
                             f"(max_event_gap={self.config.max_event_gap:g} s; cut the events there, or raise it)")
        self._t_checked = float(t[-1])

    def compile(self) -> float:
        self.compile_seconds = self.estimator.compile()
        return self.compile_seconds

    def process(self, packet: Packet) -> np.ndarray:
        tic = time.perf_counter()
        cpu_tic = time.process_time()
        if packet.still:
            self.estimator.reset()
            self._flat_run = 0
            self.last_moving = False
            self.rows.append((packet.t_ref, 0.0, 0.0, 0.0, 0, packet.span, 0, 0, True, np.nan, np.nan, False, False,
                              0.0))
            omega = np.zeros(3)
        else:
            est = self.estimator
            omega, res, cost = est.estimate(packet.events, packet.t_ref)
            looked = 0.0
            if self.lookback is not None:
                self.lookback.add(packet.events)
                looked = self._past_motion(packet)
                if not looked and self._flat_run and not est.last_flat:  # a motion after a flat packet, unconfirmed
                    est.declare_flat()
                    omega = np.zeros(3)
                if est.last_flat:
                    self._flat_run += 1
                else:
                    self._flat_run = 0
            self.last_moving = not est.last_flat or looked > 0
            self.events_processed += len(packet.events)
            self.rows.append((packet.t_ref, *omega, len(packet.events), packet.span, res.iterations,
                              res.evaluations, False, cost, est.last_gain, est.last_suspect, est.last_flat, looked))
        self.seconds += time.perf_counter() - tic
        self.cpu_seconds += time.process_time() - cpu_tic
        return omega

    def _look_back(self, packet: Packet) -> float:
        """Whether the recent past of a packet measures a motion (``frontend_flat_lookback``): the score test over
        the events of the last 4x, 16x, ... its span, up to that many seconds. Returns the span of the first lookback
        that does (0: none; the camera is still as far as the events tell)."""
        length = LOOKBACK_FACTOR * max(packet.span, self.config.frontend_min_packet_span)
        covered = packet.span
        while True:
            events = self.lookback.recent(min(length, self.lookback.span))
            if len(events) < 2 or events.duration <= 1.01 * covered:  # no events older than those already tried
                return 0.0
            if self.estimator.measures_motion(events, 0.5 * (float(events.t[0]) + float(events.t[-1]))):
                return float(events.duration)
            if length >= self.lookback.span:
                return 0.0
            covered, length = events.duration, length * LOOKBACK_FACTOR

    def _past_motion(self, packet: Packet) -> float:
        """The lookback's answer for the packet just estimated, the span that measured a motion (0: none), where one
        is needed: a flat packet (is the camera still, or moving too slowly for one packet?) and a packet that
        measures a motion right after a flat one (a start, or a false alarm: a packet of noise passes the score test
        at its 0.1 % rate, and a short run of noise packets with an isolated pass was measured to move the poses 1.8
        deg; a real start measures over the longer span too). In a run of flat packets one of LOOKBACK_EVERY looks
        back, the others take its answer. A flat packet keeps omega = 0 either way: a constant angular velocity fitted
        over a lookback is too coarse for the trajectory (its roll, the least constrained axis, 0.015-0.035 rad/s off
        on simulated starts; CMax-SLAM on a DAVIS240C pan +27 % abs error), while the back-end refines a window that
        moved (SlidingWindowBackend: a window without a measured motion gets no BA)."""
        if not self.estimator.last_flat:
            return self._look_back(packet) if self._flat_run else 0.0
        if self._flat_run % LOOKBACK_EVERY == 0:
            self._last_look = self._look_back(packet)
        return self._last_look

    def result(self) -> FrontendResult:
        arr = list(zip(*self.rows)) if self.rows else [()] * 14
        evals = np.asarray(arr[7], dtype=int)
        processed = self.events_processed
        inputs = self.input_events or self.events_read
        evaluated = self.estimator.event_evaluations
        timing = {
            "compile_seconds": self.compile_seconds,
            "wall_seconds": self.seconds,
            "cpu_seconds": self.cpu_seconds,
            # one unit everywhere: us per INPUT event (events_processed = events read, as in report.json);
            # packet_events counts each event once per (overlapping, non-still) packet that holds it
            "events_read": int(self.events_read),
            "events_processed": int(inputs),
            "us_per_event": self.seconds * 1e6 / inputs if inputs else 0.0,
            "packet_events": int(processed),
            "us_per_packet_event": self.seconds * 1e6 / processed if processed else 0.0,
            "events_evaluated": int(self.estimator.events_evaluated),
            "evaluations": int(evals.sum()),
            "zero_checks": int(self.estimator.checks),  # evaluations at omega = 0 (with the gradient when tested)
            "score_tests": int(self.estimator.score_tests),  # packets score-tested (motion_score)
            "us_per_event_per_evaluation": self.seconds * 1e6 / evaluated if evaluated else 0.0,
        }
        return FrontendResult(
            t=np.asarray(arr[0], float),
            omega=np.asarray(list(zip(arr[1], arr[2], arr[3])), float).reshape(-1, 3),
            num_events=np.asarray(arr[4], int),
            span=np.asarray(arr[5], float),
            iterations=np.asarray(arr[6], int),
            evaluations=evals,
            still=np.asarray(arr[8], bool),
            cost=np.asarray(arr[9], float),
            gain=np.asarray(arr[10], float),
            suspect=np.asarray(arr[11], bool),
            flat=np.asarray(arr[12], bool),
            lookback=np.asarray(arr[13], float),
            timing=timing,
            config=self.config,
        )


def estimate_angular_velocity(events_or_chunks, camera: Camera, config: FrontendConfig = FrontendConfig(),
                              *, dtype=np.float32, progress_total: float | None = None) -> FrontendResult:
    """Front-end on an ``Events`` object, an iterable of ``Events`` chunks (time-ordered) or a dataset with
    ``iter_events()``. Memory stays bounded by the rolling buffer. See the module docstring for the rules."""
    from ti_cmax.progress import progress

    runner = FrontendRunner(camera, config, dtype)
    runner.compile()
    chunks = downsampled(runner.counted(as_chunks(events_or_chunks)), int(config.frontend_event_sample_rate))
    bar = progress(total=progress_total, desc="front-end", unit="s")
    t_prev = None
    try:
        for packet in runner.slicer(chunks):
            runner.process(packet)
            if t_prev is not None:
                bar.update(packet.t_ref - t_prev)
            t_prev = packet.t_ref
    finally:
        bar.close()
    return runner.result()


def report_parameters(config: FrontendConfig) -> dict:
    return config_to_dict(config)


__all__ = ["FrontendResult", "PacketSlicer", "Packet", "Lookback", "AngularVelocityEstimator",
           "estimate_angular_velocity", "SLICING_RULES", "FrontendRunner", "as_chunks", "downsampled"]
