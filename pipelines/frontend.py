"""CMax-omega front-end (paper Sec. II-B, III-C1): angular velocity at equispaced times by contrast maximisation.

Data flow: a stream of ``Events`` chunks -> rolling buffer (:class:`PacketSlicer`) -> one :class:`Packet` per
timestamp t_j = t_first + dt/2 + j dt (dt = ``dt_ang_vel``) -> omega_j maximising the contrast of the packet's image
of warped events, warm-started from the previous packets (:class:`AngularVelocityEstimator`) -> integrated to a
rotation trajectory, R(t_0) = I (:class:`FrontendResult`).

Slicing (``frontend_slicing``): a packet holds the N = ``num_events_per_packet`` events centred on t_j (and every
event of ``frontend_min_packet_span`` at high event rates). Where they span more than W = ``still_span_factor *
dt_ang_vel`` the event rate is low: the ``"paper"`` rule declares the camera still; the ``"bounded"`` rule (default)
keeps the events within t_j +- W/2, and the packet is sparse (omega = 0) only when they are fewer than
``frontend_min_event_rate * W``. So one N serves slow and fast phases alike. N, the thinning cap and the rate floor
default to values derived from the sensor's pixel count (``sensor_defaults``), so that the image of warped events
holds as many events per pixel on any sensor. On large sensors that image is coarser than the sensor
(``frontend_iwe_downsample`` d: an IWE pixel covers d x d sensor pixels, :func:`iwe_intrinsics`), with the blur
kept at its width in sensor pixels.

Cost per packet is bounded at any event rate: a packet above ``frontend_max_packet_events`` is thinned 1 of k (its
span, hence the motion that makes omega measurable, is kept); so is the cost per input event: a packet stretched to
the minimum span shares its events with the packets around it and keeps at most max(2N, its event rate x dt)
(:meth:`AngularVelocityEstimator.thinning_step`). The optimiser (``frontend_optimizer``: BFGS carrying
its inverse Hessian from packet to packet, or the reference's Fletcher-Reeves CG) starts from the linear prediction
2 omega_{j-1} - omega_{j-2} (``frontend_warm_start``), usually a fraction of a pixel from the optimum.

Scaling, so that the optimiser's tolerances mean the same across packet sizes and sensors: it sees x = omega * s with
s = f * max_k |dt_k| (f: the IWE's mean focal length), the displacement in IWE pixels of the packet's farthest-in-time
event, and the cost C / mu0^2 with mu0 = n / (IWE width * height) the mean IWE value: the squared coefficient of
variation of the IWE. Integer pixels are dithered by up to half a (sensor) pixel (:class:`PixelDither`) so that the
pixel grid does not pull slow motions to omega = 0.

Contrast maximisation returns an optimum also where the events do not constrain omega; the rules that tell a
measured motion from noise (score test, lookbacks, gain check) are in ``frontend_policies`` and their outcome per
packet is a :class:`~ti_cmax.pipelines.motion.Motion`.
"""
from __future__ import annotations

import functools
import time
from dataclasses import dataclass, field, replace
from typing import Iterable, Iterator

import numpy as np

from ti_cmax import so3
from ti_cmax.camera import Camera
from ti_cmax.config import SLICING_RULES, FrontendConfig, config_to_dict
from ti_cmax.errors import InputError
from ti_cmax.events import EventBuffer, Events
from ti_cmax.kernels.iwe import IWEWorkspace, grid_bearings_numpy, grid_nodes
from ti_cmax.trajectory import Trajectory

from . import frontend_policies as policies
from .frontend_policies import Lookback, LookbackTest
from .hot_pixels import HotPixelFilter
from .motion import Motion
from .optim import CGResult, bfgs, fletcher_reeves
from .sensor_defaults import iwe_size, resolve_frontend


NO_MOTION_MEASURABLE = ("the events span no time (no events, or all at one timestamp): no packet, so no angular "
                        "velocity, can be estimated")


@dataclass(frozen=True)
class Estimate:
    """What :meth:`AngularVelocityEstimator.estimate` finds for one packet."""

    omega: np.ndarray  # (3,) rad/s, camera frame; 0 when flat
    optimum: CGResult  # the optimiser's result: x in pixels of motion, fun the normalised contrast
    motion: Motion  # MOVING, or FLAT: the events measure no motion and the optimum is noise
    gain: float = np.nan  # contrast at the optimum over that at omega = 0 (nan: not a gain check's packet)
    suspect: bool = False  # the optimum moves events by >= 1 px but barely sharpens the IWE (policies.is_suspect)

    @property
    def cost(self) -> float:
        """Normalised contrast at the optimum."""
        return self.optimum.fun

    @property
    def iterations(self) -> int:
        return self.optimum.iterations

    @property
    def evaluations(self) -> int:
        return self.optimum.evaluations


@dataclass(frozen=True)
class PacketResult:
    """The front-end's outcome for one packet (a row of :class:`FrontendResult`)."""

    t_ref: float
    omega: np.ndarray  # (3,) rad/s; 0 unless ``motion`` is MOVING
    motion: Motion
    num_events: int  # events in the packet (0 when sparse)
    span: float  # time span of the packet's events (s)
    lookback: float = 0.0  # span (s) of the lookback that measured a motion around the packet (0: none)
    estimate: Estimate | None = None  # None when sparse (nothing estimated)


@dataclass(frozen=True, eq=False)
class FrontendResult:
    """Angular velocity per packet and what happened in each packet."""

    t: np.ndarray  # (M,) packet timestamps t_j (s)
    omega: np.ndarray  # (M, 3) rad/s, camera frame
    motion: np.ndarray  # (M,) Motion per packet (object array)
    num_events: np.ndarray  # (M,) events in the packet (0 when sparse)
    span: np.ndarray  # (M,) time span of the selected packet (s)
    iterations: np.ndarray  # (M,) optimiser line searches
    evaluations: np.ndarray  # (M,) contrast+gradient evaluations
    cost: np.ndarray  # (M,) normalised contrast at the solution (nan when sparse)
    gain: np.ndarray  # (M,) contrast at the solution over the contrast at omega = 0 (nan when sparse or unchecked)
    suspect: np.ndarray  # (M,) bool: the solution moves events by >= 1 px but barely sharpens the IWE
    lookback: np.ndarray  # (M,) span (s) of the lookback that measured a motion around the packet (0: none)
    timing: dict = field(default_factory=dict)  # compile_seconds, wall_seconds, us_per_event, ...
    config: FrontendConfig = field(default_factory=FrontendConfig)
    hot_pixels: dict = field(default_factory=dict)  # the ingest's hot-pixel filter (pipelines/hot_pixels.py)

    def __len__(self) -> int:
        return len(self.t)

    def _is(self, members) -> np.ndarray:
        return np.fromiter((m in members for m in self.motion), bool, len(self.motion))

    @property
    def still(self) -> np.ndarray:
        """(M,) bool: no motion measured (``Motion.still``)."""
        return self._is({m for m in Motion if m.still})

    @property
    def sparse(self) -> np.ndarray:
        """(M,) bool: too few events to estimate (the slicer's rate floor)."""
        return self._is({Motion.SPARSE})

    @property
    def flat(self) -> np.ndarray:
        """(M,) bool: estimated, but the events measure no motion over the packet: omega = 0 (``Motion.flat``)."""
        return self._is({m for m in Motion if m.flat})

    @property
    def status(self) -> str:
        """"suspect" when the front-end's counters say omega cannot be trusted (ti_cmax.status: most checked packets
        suspect, too few events, most packets zero at a high event rate), else "ok"."""
        from ti_cmax.status import run_status

        return run_status({"frontend": self.summary()})[0]

    @property
    def checked(self) -> np.ndarray:
        """(M,) bool: packets whose contrast gain over omega = 0 was evaluated (the gain check)."""
        return ~np.isnan(self.gain)

    def trajectory(self) -> Trajectory:
        """Integrate omega (midpoint rule on SO(3)) to R_world_from_camera at the packet times, R(t_0) = I.

        A single packet (a recording of a few ms) gets poses one packet span either side of its time as well, at its
        constant omega: alone, its time would hold one pose and its measured motion would show nowhere."""
        if len(self.t) == 0:
            raise InputError(NO_MOTION_MEASURABLE)
        if len(self.t) == 1 and self.span[0] > 0:
            dt = np.array([-self.span[0], 0.0, self.span[0]])
            return Trajectory(self.t[0] + dt, so3.exp(dt[:, None] * self.omega[0]))
        return Trajectory(self.t, so3.integrate_angular_velocity(self.t, self.omega))

    def _trust_counters(self) -> dict:
        """What ti_cmax.status reads to say whether omega can be trusted: packets holding fewer events than the still
        rule's floor (``frontend_min_event_rate`` x W: at the stream's ends, or a tiny input; omega then is noise, 40
        rad/s off on 100 events), and the median event rate (events / span) of the packets that moved and of those
        set to omega = 0 by the flat test (a still camera sees noise, far below the rate of a moving one)."""
        cfg = self.config
        floor = int(np.ceil(cfg.frontend_min_event_rate * cfg.still_span_factor * cfg.dt_ang_vel))
        estimated, flat = ~self.sparse, self.flat
        moving = estimated & ~flat
        rate = self.num_events / np.maximum(self.span, 1e-9)
        return {
            "min_packet_events": floor,
            "small_packets": int(np.count_nonzero(estimated & (self.num_events < floor))) if floor > 0 else 0,
            "event_rate": {"moving": float(np.median(rate[moving])) if np.any(moving) else None,
                           "flat": float(np.median(rate[flat])) if np.any(flat) else None,
                           "floor": float(cfg.frontend_min_event_rate)},
        }

    def summary(self) -> dict:
        """JSON-friendly summary (for report.json; "still_packets" counts the sparse packets)."""
        estimated = ~self.sparse
        return {
            "packets": int(len(self.t)),
            "still_packets": int(np.count_nonzero(self.sparse)),
            "suspect_packets": int(np.count_nonzero(self.suspect)),
            "flat_packets": int(np.count_nonzero(self.flat)),
            "lookback_packets": int(np.count_nonzero(self.lookback)),
            "checked_packets": int(np.count_nonzero(self.checked)),
            "median_contrast_gain": float(np.nanmedian(self.gain)) if np.any(estimated) else 0.0,
            "mean_iterations": float(np.mean(self.iterations)) if len(self.t) else 0.0,
            "mean_evaluations": float(np.mean(self.evaluations)) if len(self.t) else 0.0,
            "mean_packet_events": float(np.mean(self.num_events[estimated])) if np.any(estimated) else 0.0,
            **self._trust_counters(),
            **{k: (float(v) if isinstance(v, (int, float, np.floating, np.integer)) else v)
               for k, v in self.timing.items()},
        }

    @classmethod
    def from_packets(cls, rows: list[PacketResult], timing: dict, config: FrontendConfig) -> "FrontendResult":
        """Columns of the per-packet rows."""
        def column(get, dtype):
            return np.fromiter((get(r) for r in rows), dtype, len(rows))

        estimates = [r.estimate for r in rows]
        nan = float("nan")
        motion = np.empty(len(rows), object)
        motion[:] = [r.motion for r in rows]
        return cls(
            t=column(lambda r: r.t_ref, float),
            omega=np.asarray([r.omega for r in rows], float).reshape(-1, 3),
            motion=motion,
            num_events=column(lambda r: r.num_events, int),
            span=column(lambda r: r.span, float),
            iterations=np.fromiter((e.iterations if e else 0 for e in estimates), int, len(rows)),
            evaluations=np.fromiter((e.evaluations if e else 0 for e in estimates), int, len(rows)),
            cost=np.fromiter((e.cost if e else nan for e in estimates), float, len(rows)),
            gain=np.fromiter((e.gain if e else nan for e in estimates), float, len(rows)),
            suspect=np.fromiter((e.suspect if e else False for e in estimates), bool, len(rows)),
            lookback=column(lambda r: r.lookback, float),
            timing=timing,
            config=config,
        )


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
    """The events around one timestamp t_j (the slicer's output)."""

    t_ref: float
    events: Events  # the selected events (empty when sparse)
    span: float  # their time span (s)
    sparse: bool = False  # too few events around t_ref to estimate omega (Motion.SPARSE)


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
        self._store = EventBuffer()  # the buffer's events; self._buf: a view of them
        self._buf = Events.empty()
        self._pending: list[Events] = []  # chunks pushed since the buffer was last joined (joined when a packet is due)
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
        # the buffer is joined only when a packet may be final (a live source pushes many small chunks, and a join
        # copies the whole buffer); _known() on the parts equals it on the joined buffer
        if not self._known():
            return
        self._join(trim=True)
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

    def _join(self, trim: bool = False) -> None:
        """Append the pending chunks to the buffer (``EventBuffer``: each event is copied once; packets are views).
        ``trim`` (the packet at t_ref is final, it is emitted next): first leave out the events before its first one,
        which ``_emit`` would drop after it anyway (at high event rates most events can fall between packets)."""
        if not self._pending:
            return
        parts = self._pending
        if trim:
            before = lambda t: sum(int(e.index_at(t)) for e in (self._buf, *parts))  # noqa: E731 - events before t
            skip = max(0, min(before(self.t_ref) - self.n // 2, before(self.t_ref - 0.5 * self.min_span)))
            self._store.drop(skip)
            skip -= len(self._buf)
            while parts and skip >= len(parts[0]):
                skip -= len(parts.pop(0))
            if parts and skip > 0:
                parts[0] = parts[0][skip:]
        self._buf = Events.empty()  # no view of the store left here: it may then reuse its arrays
        for part in parts:
            self._store.push(part)
        self._buf = self._store.view()
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
        sparse = False
        if span > self.window:
            if self.rule == "paper":
                sparse = True
            else:
                j0 = max(i0, int(buf.index_at(t_ref - 0.5 * self.window)))
                j1 = min(i1, int(buf.index_at(t_ref + 0.5 * self.window, side="right")))
                packet = buf[j0:j1]
                span = packet.duration
                sparse = len(packet) < self.min_events
        if len(packet) < 2 or packet.duration <= 0:
            sparse = True
        # drop what no later packet can use: the next packet starts at or after index c_next - N/2
        self.t_ref = t_ref + self.dt
        drop = max(0, min(int(buf.index_at(self.t_ref)) - half, int(buf.index_at(self.t_ref - 0.5 * self.min_span))))
        if drop > 0:
            self._store.drop(drop)
            self._buf = self._store.view()
        self.packets_emitted += 1
        return Packet(t_ref, Events.empty() if sparse else packet, span, sparse)


def iwe_intrinsics(K: np.ndarray, downsample: int) -> np.ndarray:
    """Intrinsics of an IWE whose pixel covers d x d sensor pixels: sensor pixel (i, j) spans [i - 1/2, i + 1/2], so
    IWE coordinate = (sensor coordinate + 1/2) / d - 1/2 (the sensor's edges stay the IWE's)."""
    d = float(downsample)
    Kd = np.array(K, dtype=float)
    Kd[:2, :2] /= d
    Kd[:2, 2] = (Kd[:2, 2] + 0.5) / d - 0.5
    return Kd


# A distorted camera's bearing table: a grid every GRID_STEPS[i] pixels, bilinear in between, the coarsest within
# GRID_MAX_ERROR sensor pixels of the exact bearing at every pixel (the per-pixel table, 15 MB on HD, is read at
# random: 20 ns per packed event in a front-end run, 11 from a grid every 16 pixels, 64 kB). No grid finer than 4
# pixels: at 2 the interpolation cost as much as it saved (DAVIS240C, k1 = -0.37: 15 ns per packed event either
# way), and the per-pixel table is exact. The simulated HD camera (k1 = -0.1) takes g = 16, the DAVIS240C one none.
GRID_STEPS = (16, 8, 4)
GRID_MAX_ERROR = 0.01


def bearing_grid(camera: Camera, step: int) -> np.ndarray:
    """The camera's bearings at the nodes of a grid every ``step`` pixels ((nodes, 4) float32, rows of
    ``grid_nodes(width, height, step)[0]`` nodes from pixel (0, 0); the last row and column lie past the sensor)."""
    cols, rows = grid_nodes(camera.width, camera.height, step)
    ny, nx = np.mgrid[0:rows, 0:cols] * step
    table = np.zeros((rows * cols, 4), np.float32)
    table[:, :3] = camera.unproject(nx.ravel(), ny.ravel())
    return table


def grid_step_for(camera: Camera, max_error: float = GRID_MAX_ERROR) -> int:
    """The largest step of GRID_STEPS whose bilinear grid (:func:`bearing_grid`) is within ``max_error`` sensor
    pixels of the camera's per-pixel bearings at every pixel (error in pixels: bearing error times fx, fy); 0 when
    none is (a distortion too strong to interpolate: the per-pixel table)."""
    exact = camera.bearing_lut4[:, :2].astype(np.float64)
    ys, xs = np.mgrid[0:camera.height, 0:camera.width]
    xs, ys = xs.ravel(), ys.ravel()
    for step in GRID_STEPS:
        approx = grid_bearings_numpy(bearing_grid(camera, step), xs, ys, step, camera.width, np.float64)[:, :2]
        err = np.abs(approx - exact) * [camera.fx, camera.fy]
        if np.all(np.isfinite(err)) and float(err.max()) <= max_error:
            return step
    return 0


DITHER_PERIOD = 1 << 16  # distinct offsets of the dither table (a packet's start in it: a hash of its time)


class PixelDither:
    """Sub-pixel dither of a packet's integer event pixels, as offsets of its bearings (x / fx, y / fy on the unit
    depth plane): up to ``amplitude`` px, uniform, independent per event (a fixed table of uniform draws, read from an
    offset that a packet's time picks: no per-event hashing, one add per coordinate; deterministic for a packet
    sequence, whatever the chunking).

    Why: event coordinates are integers, so at omega = 0 every event sits on a pixel centre and its bilinear vote is
    one pixel, while any motion spreads the votes over four: the contrast favours omega = 0 by a margin that does not
    depend on the motion (a pixel-grid bias of CMax). Where a packet's motion is below about a pixel (a camera starting
    or slowing down, slow star-tracker pans) the bias wins and omega is pulled to 0. Dithering each event uniformly
    over its pixel takes the grid out of the IWE."""

    def __init__(self, camera: Camera, amplitude: float, dtype, size: int = 0):
        self.amplitude, self.dtype = float(amplitude), np.dtype(dtype)
        self.fx, self.fy = camera.fx, camera.fy
        self._grow(max(int(size), 1))

    def _grow(self, size: int) -> None:
        rng = np.random.default_rng(20261203)
        u = rng.uniform(-self.amplitude, self.amplitude, (DITHER_PERIOD + size, 2))
        self.table = (u / [self.fx, self.fy]).astype(self.dtype)  # (rows, 2): x / fx, y / fy

    def offset(self, n: int, t_ref: float) -> int:
        """The table row a packet of n events centred on t_ref starts at (the table grows to hold it)."""
        if n > len(self.table) - DITHER_PERIOD:
            self._grow(n)
        return (int(round(t_ref * 1e5)) * 40503) % DITHER_PERIOD

    def rows(self, n: int, t_ref: float) -> np.ndarray:
        """The (n, 2) bearing offsets of such a packet's events (kernel ``pack`` adds them to x, y)."""
        offset = self.offset(n, t_ref)
        return self.table[offset:offset + n]


# ------------------------------------------------------------------------------------------------
# per-packet estimation
# ------------------------------------------------------------------------------------------------

class AngularVelocityEstimator:
    """Estimates omega for one packet at a time (keeps the compiled workspace and the warm start)."""

    def __init__(self, camera: Camera, config: FrontendConfig = FrontendConfig(), dtype=np.float32):
        config = resolve_frontend(config, camera)
        self.camera, self.config = camera, config
        d = int(config.frontend_iwe_downsample)
        self.iwe_width, self.iwe_height = iwe_size(camera, d)
        self.K = iwe_intrinsics(camera.K, d)
        self.focal = 0.5 * (self.K[0, 0] + self.K[1, 1])  # of the IWE: optimiser steps are in IWE pixels
        cap = config.num_events_per_packet
        if config.frontend_max_packet_events > 0:
            cap = max(cap, config.frontend_max_packet_events)
        # the blur keeps its width in sensor pixels (its angle): sigma / d IWE pixels
        self.ws = IWEWorkspace(self.iwe_width, self.iwe_height, dtype, config.frontend_blur_sigma / d,
                               capacity=cap)
        # integer pixels are dithered (PixelDither: the pixel grid's bias towards omega = 0); float ones are not
        self.dither = PixelDither(camera, config.frontend_pixel_dither, dtype, cap) \
            if config.frontend_pixel_dither > 0 else None
        self.omega = np.zeros(3)
        self.omega_prev = None  # omega of the packet before the last one (linear warm start)
        self.inv_hessian = None  # BFGS: carried from packet to packet (x = pixels of motion, cost normalised)
        self.events_evaluated = 0  # events actually used in the optimisation (after thinning)
        self.event_evaluations = 0  # sum over packets of events used x evaluations (for the cost per event-evaluation)
        self.packets_estimated = 0  # packets estimated so far (the gain check runs on 1 of frontend_gain_check_every)
        self.flat_packets = 0  # packets whose omega was set to 0 as flat (declare_flat)
        self.checks = 0  # evaluations at omega = 0 (cost only unless score-tested)
        self.score_tests = 0  # score tests of omega = 0 (policies.motion_score)

    def reset(self) -> None:
        """Forget the warm start (after a sparse or flat packet)."""
        self.omega = np.zeros(3)
        self.omega_prev = None

    def thinning_step(self, events: Events, packet: bool = False) -> int:
        """k of the 1-of-k thinning: k = ceil(n / m), m = ``frontend_max_packet_events`` (k = 1: no thinning; a cap
        <= 0 never thins). A ``packet`` (the slicer's, not a lookback's) keeps at most m' = max(2N, n dt / span)
        events when fewer than m (N = ``num_events_per_packet``, dt = ``dt_ang_vel``): a packet of more than 2N
        events spans the minimum span S (``frontend_min_packet_span``) and shares each event with S / dt packets,
        so m' keeps the events evaluated per second of data at the input rate, each input event evaluated about
        once per evaluation round whatever S / dt; never fewer than the reference's thinning cap, 2N (see
        ``sensor_defaults``, ``frontend_max_packet_events``)."""
        cfg = self.config
        cap = int(cfg.frontend_max_packet_events)
        n = len(events)
        if cap <= 0 or n <= 1:
            return 1
        floor = 2 * int(cfg.num_events_per_packet)
        if packet and n > floor:
            span = float(events.t[-1]) - float(events.t[0])
            if span > cfg.dt_ang_vel:
                cap = min(cap, max(floor, int(np.ceil(n * cfg.dt_ang_vel / span))))
        return -(-n // cap) if n > cap else 1

    def thin(self, events: Events, packet: bool = False) -> Events:
        """Keep 1 of k events (:meth:`thinning_step`); uniform in the event index, so the span and the event density
        pattern are kept."""
        k = self.thinning_step(events, packet)
        return events[(k // 2)::k] if k > 1 else events

    def warm_start(self) -> np.ndarray:
        if self.config.frontend_warm_start == "linear" and self.omega_prev is not None:
            return 2.0 * self.omega - self.omega_prev
        return self.omega

    def compile(self) -> float:
        """Compile (or load from the offline cache) the kernels and build the bearing table ``pack`` reads (0.5 s for
        a distorted HD camera: paid before the first packet, not by it); returns seconds spent."""
        t0 = time.perf_counter()
        self.ws.compile()
        _ = self._lut
        return time.perf_counter() - t0

    @functools.cached_property
    def _lut(self) -> np.ndarray:
        """The bearings kernel ``pack`` reads, in the workspace's float type (:meth:`IWEWorkspace.pack`): for an
        undistorted camera the separable form of its per-pixel table (row i holds the x bearing of column i, the y
        bearing of row i and 1, the numbers of the per-pixel table); for a distorted one a grid of its bearings
        (:func:`bearing_grid`, step ``_grid``), or where no grid is within GRID_MAX_ERROR the per-pixel table
        (pixels, 4)."""
        cam = self.camera
        if not cam.has_distortion:
            lut = cam.separable_bearing_lut4
        elif self._grid:
            lut = bearing_grid(cam, self._grid)
        else:
            lut = cam.bearing_lut4
        return lut if lut.dtype == self.ws.dtype else lut.astype(self.ws.dtype)

    @functools.cached_property
    def _grid(self) -> int:
        """Step of the bearing grid ``pack`` interpolates for a distorted camera (:func:`grid_step_for`; 0: the
        per-pixel table, or an undistorted camera's separable table)."""
        return grid_step_for(self.camera) if self.camera.has_distortion else 0

    def _load(self, events: Events, t_ref: float, packet: bool = False) -> tuple[int, float]:
        """Upload a packet, thinned (1 of k, :meth:`thinning_step`, as :meth:`thin`), into the workspace; returns
        (events loaded, max |t - t_ref|). Integer pixels go through kernel ``pack`` (table bearings, dither and
        times read from the events' arrays in place); sub-pixel ones are undistorted here."""
        total = len(events)
        k = self.thinning_step(events, packet)
        start = k // 2 if k > 1 else 0
        n = len(range(start, total, k))
        if n and not events.has_subpixel_coordinates:
            offset = self.dither.offset(n, t_ref) if self.dither is not None else 0
            return n, self.ws.pack(events.t, events.x, events.y, self._lut, self.camera.width, start, k, n, t_ref,
                                   None if self.dither is None else self.dither.table, offset,
                                   separable=not self.camera.has_distortion, grid=self._grid)
        events = self.thin(events, packet)
        packed = np.ascontiguousarray(self.camera.bearings(events.x, events.y, dtype=self.ws.dtype, columns=4).T)
        np.subtract(events.t, t_ref, out=packed[3], casting="unsafe")
        self.ws.set_packed(packed)
        return n, self.ws.dt_max

    def _objective(self, events: Events, t_ref: float, packet: bool = False):
        """Load events (thinned; ``packet``: the slicer's packet, :meth:`thinning_step`); returns (fun, s, n): fun(x)
        = normalised contrast and gradient at omega = x / s, s = focal * max |t - t_ref| (pixels per rad/s, so
        optimiser steps are in pixels of motion blur)."""
        n, span = self._load(events, t_ref, packet)
        self.events_evaluated += n
        s = self.focal * span if n else 0.0
        if not s > 0:
            raise InputError("packet has no time extent")
        mu0 = n / float(self.iwe_width * self.iwe_height)
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
                max_condition=policies.BFGS_MAX_CONDITION)
            return res
        return fletcher_reeves(
            fun, x0, maximize=True, init_step=cfg.frontend_cg_init_step,
            line_search_tol=cfg.frontend_cg_line_search_tol, max_iter=cfg.frontend_cg_max_iters,
            grad_tol=cfg.frontend_cg_grad_tol, rel_cost_tol=cfg.frontend_cg_rel_cost_tol,
            max_line_evals=cfg.frontend_cg_max_line_evals, step_guess=cfg.frontend_cg_step_guess,
        )

    def estimate(self, events: Events, t_ref: float, omega0=None) -> Estimate:
        """The packet step (paper Sec. III-C): the packet's events, around t_ref, are warped to t_ref by the
        rotation at omega; omega maximises the variance of their image (the IWE), starting from the warm start (or
        ``omega0``). The policies then say whether the events measure that motion (:meth:`_judge`): a flat packet
        takes omega = 0 and resets the warm start."""
        fun, s, n = self._objective(events, t_ref, packet=True)
        x0 = (self.warm_start() if omega0 is None else np.asarray(omega0, float)) * s
        optimum = self._maximize(fun, x0)
        self.omega_prev, self.omega = self.omega, optimum.x / s
        motion, gain, suspect, extra = self._judge(events, t_ref, optimum, x0)
        if motion is Motion.FLAT:
            self.declare_flat()
        self.event_evaluations += n * (optimum.evaluations + extra)
        return Estimate(self.omega.copy(), optimum, motion, gain, suspect)

    def _judge(self, events: Events, t_ref: float, optimum: CGResult, x0: np.ndarray):
        """The packet's Motion (MOVING or FLAT), its gain (nan unless a gain check's packet), whether it is suspect,
        and the evaluations spent at omega = 0. x (the optimiser's variable) is the displacement in pixels of the
        packet's farthest-in-time event, so ``moved`` and ``jump`` are pixels."""
        cfg = self.config
        scheduled = policies.gain_check_due(self.packets_estimated, cfg)
        self.packets_estimated += 1
        moved = float(np.linalg.norm(optimum.x))
        tested = cfg.frontend_flat_is_still and policies.needs_score_test(moved, float(np.linalg.norm(optimum.x - x0)))
        gain, suspect, extra, g_zero = np.nan, False, 0, None
        if scheduled or tested:
            c_zero, g_zero = self._at_zero(with_grad=tested)
            extra += 1
            if scheduled:  # the run's status counts the gain checks only (an even sample of the packets)
                gain = float(optimum.fun / c_zero) if c_zero > 0 else np.inf
                suspect = policies.is_suspect(moved, gain, cfg)
                if suspect and cfg.frontend_flat_is_still and not tested:
                    tested, g_zero = True, self._at_zero(with_grad=True)[1]
                    extra += 1
        flat = tested and not self._significant(g_zero) and not self._fast_motion(events, t_ref, moved)
        return (Motion.FLAT if flat else Motion.MOVING), gain, suspect, extra

    def _at_zero(self, with_grad: bool) -> tuple[float, np.ndarray]:
        """Normalised contrast (and gradient, for the score test) at omega = 0 of the loaded packet."""
        c_zero, g_zero, _ = self.ws.evaluate(np.zeros(3), self.K, self.config.contrast_measure, with_grad=with_grad)
        self.checks += 1
        return c_zero * self._scale, g_zero

    def measures_motion(self, events: Events, t_ref: float) -> bool:
        """Whether ``events`` (e.g. a lookback: a longer span ending with a flat packet) measure any motion: the
        score test of omega = 0 over them (one evaluation)."""
        n = self._objective(events, t_ref)[2]
        g_zero = self.ws.evaluate(np.zeros(3), self.K, self.config.contrast_measure)[1]
        self.checks += 1
        self.event_evaluations += n
        return self._significant(g_zero)

    def _fast_motion(self, events: Events, t_ref: float, moved: float) -> bool:
        """A fast packet failing the score test: whether the test passes over a sub-span
        (``policies.fast_motion_span``)."""
        sub = policies.fast_motion_span(events, t_ref, moved)
        return sub is not None and self.measures_motion(sub, t_ref)

    def _significant(self, g_zero) -> bool:
        """The score test of omega = 0 on the loaded events passes: they measure a motion."""
        self.score_tests += 1
        return self.motion_score(g_zero) >= self.config.frontend_min_motion_score

    def motion_score(self, g_zero) -> float:
        """``policies.motion_score`` of the loaded packet, g_zero its gradient at omega = 0 (the workspace's last
        evaluation, whose per-event terms give the noise covariance)."""
        return policies.motion_score(g_zero, self.ws.gradient_covariance())

    def declare_flat(self) -> None:
        """The last packet is flat: omega = 0 and the warm start reset (a flat :meth:`estimate`, or one whose motion
        its lookback does not confirm)."""
        self.flat_packets += 1
        self.reset()

    def contrast_ratio(self, events: Events, t_ref: float, omega) -> tuple[float, np.ndarray]:
        """How well ``omega`` (another method's angular velocity) explains one packet: its contrast over the best
        contrast CG finds from the better of ``omega`` and the warm start (1: a local optimum; well below 1: the
        events say the motion differs). Returns (ratio, best omega); the best becomes the warm start."""
        fun, s, n = self._objective(events, t_ref, packet=True)
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

    ``slicer(chunks)`` yields packets, ``process(packet)`` returns the packet's :class:`PacketResult` and records it,
    ``result()`` assembles the :class:`FrontendResult` with timing (compile time apart from steady state).
    """

    def __init__(self, camera: Camera, config: FrontendConfig = FrontendConfig(), dtype=np.float32):
        config = resolve_frontend(config, camera)
        self.config = config
        self.estimator = AngularVelocityEstimator(camera, config, dtype)
        self.slicer = PacketSlicer(config)
        self.width, self.height = camera.width, camera.height
        self._t_checked: float | None = None  # the last event time check() saw
        # score tests over a packet's recent past, where one packet cannot tell (LookbackTest)
        self.lookbacks = LookbackTest(config, self.estimator.measures_motion) \
            if config.frontend_flat_lookback > 0 and config.frontend_flat_is_still else None
        self.rows: list[PacketResult] = []
        self.events_processed = 0  # events in non-sparse packets (each counted once per packet): packet_events
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
        stray event or a clock jump: bridging it costs time in proportion to the pause). The readers check files
        already; this guards the Python API."""
        if len(chunk) == 0:
            return
        t = chunk.t
        # one pass per array on good input (a non-decreasing run between finite ends is finite, and a NaN fails the
        # comparison); anything else goes through Events.validate, which names the first bad event
        if chunk.has_subpixel_coordinates:  # undistorted coordinates (star tracking) may fall off the sensor
            chunk.validate(source="events")
        elif not (np.isfinite(t[0]) and np.isfinite(t[-1]) and bool(np.all(t[1:] >= t[:-1]))
                  and int(chunk.x.max()) < self.width and int(chunk.y.max()) < self.height):
            chunk.validate(self.width, self.height, source="events")
        if self._t_checked is not None and t[0] < self._t_checked:
            raise InputError(f"event chunks are not in time order (t={float(t[0])!r} after {self._t_checked!r})")
        first = self._t_checked if self._t_checked is not None else float(t[0])
        if float(t[-1]) - first <= self.config.max_event_gap:  # no pause within can be longer: nothing to search
            self._t_checked = float(t[-1])
            return
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


    def process(self, packet: Packet) -> PacketResult:
        """Estimate one packet (nothing when sparse), record and return its result."""
        tic = time.perf_counter()
        cpu_tic = time.process_time()
        row = self._sparse(packet) if packet.sparse else self._estimate(packet)
        self.rows.append(row)
        self.seconds += time.perf_counter() - tic
        self.cpu_seconds += time.process_time() - cpu_tic
        return row

    def _sparse(self, packet: Packet) -> PacketResult:
        """Too few events: omega = 0, and the warm start and the run of flat packets end."""
        self.estimator.reset()
        if self.lookbacks is not None:
            self.lookbacks.flat_run = 0
        return PacketResult(packet.t_ref, np.zeros(3), Motion.SPARSE, 0, packet.span)

    def _estimate(self, packet: Packet) -> PacketResult:
        """The packet step, then the lookback's word on its motion (``frontend_policies.LookbackTest``)."""
        estimate = self.estimator.estimate(packet.events, packet.t_ref)
        motion, looked = estimate.motion, 0.0
        if self.lookbacks is not None:
            motion, looked = self.lookbacks.confirm(packet.events, packet.span, motion)
            if motion is Motion.UNCONFIRMED:
                self.estimator.declare_flat()
        omega = estimate.omega if motion is Motion.MOVING else np.zeros(3)
        self.events_processed += len(packet.events)
        return PacketResult(packet.t_ref, omega, motion, len(packet.events), packet.span, looked, estimate)

    def result(self) -> FrontendResult:
        processed = self.events_processed
        inputs = self.input_events or self.events_read
        evaluated = self.estimator.event_evaluations
        evaluations = sum(r.estimate.evaluations for r in self.rows if r.estimate is not None)
        timing = {
            "compile_seconds": self.compile_seconds,
            "wall_seconds": self.seconds,
            "cpu_seconds": self.cpu_seconds,
            # one unit everywhere: us per INPUT event (events_processed = events read, as in report.json);
            # packet_events counts each event once per (overlapping, non-sparse) packet that holds it
            "events_read": int(self.events_read),
            "events_processed": int(inputs),
            "us_per_event": self.seconds * 1e6 / inputs if inputs else 0.0,
            "packet_events": int(processed),
            "us_per_packet_event": self.seconds * 1e6 / processed if processed else 0.0,
            "events_evaluated": int(self.estimator.events_evaluated),
            "evaluations": int(evaluations),
            "zero_checks": int(self.estimator.checks),  # evaluations at omega = 0 (with the gradient when tested)
            "score_tests": int(self.estimator.score_tests),  # score tests of omega = 0 (policies.motion_score)
            "us_per_event_per_evaluation": self.seconds * 1e6 / evaluated if evaluated else 0.0,
        }
        return FrontendResult.from_packets(self.rows, timing, self.config)


def estimate_angular_velocity(events_or_chunks, camera: Camera, config: FrontendConfig = FrontendConfig(),
                              *, dtype=np.float32, progress_total: float | None = None) -> FrontendResult:
    """Front-end on an ``Events`` object, an iterable of ``Events`` chunks (time-ordered) or a dataset with
    ``iter_events()``. Memory stays bounded by the rolling buffer. See the module docstring for the rules."""
    from ti_cmax.progress import StageBars, stage

    with stage("start-up and compile"):
        runner = FrontendRunner(camera, config, dtype)
        runner.compile()
    hot_pixels = HotPixelFilter(camera.width, camera.height, config)
    chunks = downsampled(hot_pixels.filter(runner.counted(as_chunks(events_or_chunks))),
                         int(config.frontend_event_sample_rate))
    with StageBars(progress_total, ("front-end",)) as bars:
        for packet in runner.slicer(chunks):
            bars.start(packet.events.t[0] if len(packet.events) else packet.t_ref)
            runner.process(packet)
            bars.at("front-end", packet.t_ref)
        bars.done()
    return replace(runner.result(), hot_pixels=hot_pixels.summary())


def report_parameters(config: FrontendConfig) -> dict:
    return config_to_dict(config)


__all__ = ["FrontendResult", "PacketSlicer", "Packet", "PacketResult", "Estimate", "Motion", "Lookback",
           "AngularVelocityEstimator", "estimate_angular_velocity", "SLICING_RULES", "FrontendRunner", "as_chunks",
           "downsampled"]
