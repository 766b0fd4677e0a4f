"""Pieces shared by the event readers: per-block validation with file positions, re-chunking, time cuts.

Readers yield raw blocks of any size as ``Block(events, lines, first_index)``; ``lines`` holds the 1-based line
number of each event for text files (None for indexed formats). ``validated_chunks`` checks every block against
the sensor size and the previous block's last timestamp (so unsorted data across block borders is caught), cuts
the requested time range and re-slices into chunks of exactly ``chunk_size`` events (the last may be shorter).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Iterable, Iterator

import numpy as np

from ..camera import SENSORS
from ..errors import InputError
from ..events import Events, signed_polarity


@dataclass
class Block:
    events: Events
    lines: np.ndarray | None  # 1-based line number of each event (text files with comments) or None
    first_index: int  # index of the first event of the block in the file
    line0: int | None = None  # text files without comments: event i is on line line0 + i
    nlines: int = 0  # text files: newlines in the block


def grouped_blocks(arrays, block: int, make_events) -> Iterator[Block]:
    """Group record arrays (one per message/packet) into Blocks of at least ``block`` events; ``make_events``
    turns the concatenated records into Events. Used by the message-based formats (ROS bags, AEDAT4)."""
    parts, n, first = [], 0, 0
    for arr in arrays:
        if len(arr):
            parts.append(arr)
            n += len(arr)
        if n >= block:
            yield Block(make_events(np.concatenate(parts)), None, first)
            first += n
            parts, n = [], 0
    if parts:
        yield Block(make_events(np.concatenate(parts)), None, first)


def is_decoder_error(exc: BaseException) -> bool:
    """An exception of a compiled decoder (faery, aedat): ordinary ones, and Rust panics (pyo3's PanicException is
    a BaseException); never KeyboardInterrupt, SystemExit or GeneratorExit."""
    return isinstance(exc, Exception) or type(exc).__name__ == "PanicException"


class NoCompanions:
    """Reader mixin: the events file carries no intrinsics, IMU or ground truth."""

    def camera(self):
        return None

    def imu(self):
        return None

    def groundtruth(self):
        return None


class ScannedSource(NoCompanions):
    """Base of the readers of files without an index (AEDAT4, Prophesee RAW): ``_arrays()`` yields record
    arrays (field ``t`` in microseconds); time range and event count come from one pass over them, cached."""

    _summary = None

    def _arrays(self) -> Iterator[np.ndarray]:  # pragma: no cover - abstract
        raise NotImplementedError

    @staticmethod
    def _events(a: np.ndarray) -> Events:
        """Records with fields t (us), x, y, on (bool) -> Events."""
        return Events(a["t"].astype(np.float64) * 1e-6, a["x"], a["y"], signed_polarity(a["on"]))

    def _scan(self):
        if self._summary is None:
            n, t0, t1 = 0, None, None
            for a in self._arrays():
                if len(a):
                    t0 = a["t"][0] if t0 is None else t0
                    t1 = a["t"][-1]
                    n += len(a)
            self._summary = (n, t0, t1)
        return self._summary

    def time_range(self):
        n, t0, t1 = self._scan()
        if n == 0:
            raise InputError("the file holds no events", source=self.source)
        return float(t0) * 1e-6, float(t1) * 1e-6

    def num_events(self) -> int:
        return self._scan()[0]


# times read in an assumed unit are refused when what they imply is beyond any recording: a duration over this
# (s; microseconds read as seconds: 1 s of data spans 11.6 days) or, over at least MIN_EVENTS_FOR_RATE events, a mean
# event rate over this (events/s; seconds or milliseconds read as microseconds), more than the readout of any event
# camera
MAX_DURATION = 1e5
MAX_EVENT_RATE = 1e9
MIN_EVENTS_FOR_RATE = 1000


def check_time_span(first: float, last: float, n: int | None, source: str, what: str, fix: str) -> None:
    """Raise InputError when times ``first``..``last`` (s) of ``n`` events (None: not known cheaply) imply a duration
    or an event rate no recording has. ``what`` names the times and the unit they were read in; ``fix`` says what to
    set (an attribute, an option)."""
    span = last - first
    if not np.isfinite(span) or span < 0:  # unsorted or NaN: the block validation names the event
        return
    if span > MAX_DURATION:
        raise InputError(f"{what}, the events span {span:.4g} s ({span / 86400:.3g} days): longer than any recording "
                         f"(at most {MAX_DURATION:g} s); {fix}", source=source)
    if n is not None and n >= MIN_EVENTS_FOR_RATE and (span == 0 or n / span > MAX_EVENT_RATE):
        rate = "an infinite rate" if span == 0 else f"{n / span:.3g} events/s"
        raise InputError(f"{what}, {n} events span {span:.3g} s ({rate}): more than any event camera outputs (at most "
                         f"{MAX_EVENT_RATE:.0e} events/s); {fix}", source=source)


def _where(block: Block, i: int) -> dict:
    if block.lines is not None:
        return {"line": int(block.lines[i])}
    if block.line0 is not None:
        return {"line": block.line0 + i}
    return {"index": block.first_index + i}


def _raise(source: str, block: Block, i: int, message: str):
    w = _where(block, i)
    if "line" in w:
        raise InputError(message, source=source, line=w["line"])
    raise InputError(f"event {w['index']}: {message}", source=source)


def validate_block(block: Block, source: str, width: int | None, height: int | None, prev_t: float | None):
    """Raise InputError (naming file and line or event index) on NaN, unsorted time, pixels off the sensor."""
    ev = block.events
    if len(ev) == 0:
        return
    t = ev.t
    # good blocks in one pass per column: finite ends and non-decreasing steps make every time finite (a NaN fails
    # every comparison), and the largest pixel bounds them all; anything else is searched for the first bad event
    integer = not ev.has_subpixel_coordinates
    if np.isfinite(t[0]) and np.isfinite(t[-1]) and (prev_t is None or t[0] >= prev_t) \
            and bool(np.greater_equal(t[1:], t[:-1]).all()) and integer \
            and (width is None or int(ev.x.max()) < width) and (height is None or int(ev.y.max()) < height):
        return
    bad = ~np.isfinite(t)
    if bad.any():
        i = int(np.argmax(bad))
        _raise(source, block, i, f"timestamp is not a finite number ({float(t[i])})")
    if prev_t is not None and t[0] < prev_t:
        _raise(source, block, 0, f"timestamps are not sorted: t={float(t[0])!r} comes after t={float(prev_t)!r}")
    dec = t[1:] < t[:-1]
    if dec.any():
        i = int(np.argmax(dec)) + 1
        _raise(source, block, i, f"timestamps are not sorted: t={float(t[i])!r} comes after t={float(t[i - 1])!r}")
    for name, arr, limit in (("x", ev.x, width), ("y", ev.y, height)):
        if not integer:
            nf = ~np.isfinite(arr)
            if nf.any():
                i = int(np.argmax(nf))
                _raise(source, block, i, f"{name} is not a finite number")
        if limit is None:
            continue
        out = (arr < 0) | (arr >= limit) if not integer else arr >= limit
        if out.any():
            i = int(np.argmax(out))
            _raise(source, block, i, f"{name}={arr[i]} is outside the sensor (expected 0 <= {name} < {limit})")


def validated_chunks(
    blocks: Iterable[Block],
    source: str,
    width: int | None,
    height: int | None,
    chunk_size: int,
    t_start: float | None = None,
    t_end: float | None = None,
) -> Iterator[Events]:
    """Validate raw blocks, keep t_start <= t < t_end, and re-slice into chunks of ``chunk_size`` events."""
    if chunk_size < 1:
        raise InputError(f"chunk_size must be >= 1, got {chunk_size}")
    pending: list[Events] = []
    n_pending = 0
    prev_t = None
    for block in blocks:
        validate_block(block, source, width, height, prev_t)
        ev = block.events
        if len(ev) == 0:
            continue
        prev_t = float(ev.t[-1])
        if t_start is not None and ev.t[-1] < t_start:
            continue
        done = t_end is not None and ev.t[-1] >= t_end
        if t_start is not None or t_end is not None:
            i0 = int(np.searchsorted(ev.t, t_start, "left")) if t_start is not None else 0
            i1 = int(np.searchsorted(ev.t, t_end, "left")) if t_end is not None else len(ev)
            ev = ev[i0:i1]
        # only a chunk that straddles two blocks is a copy; the others are views of their block
        if n_pending:
            take = min(chunk_size - n_pending, len(ev))
            pending.append(ev[:take])
            n_pending += take
            ev = ev[take:]
            if n_pending == chunk_size:
                yield Events.concatenate(pending)
                pending, n_pending = [], 0
        if not n_pending:
            whole = len(ev) - len(ev) % chunk_size
            for i in range(0, whole, chunk_size):
                yield ev[i:i + chunk_size]
            if whole < len(ev):
                pending, n_pending = [ev[whole:]], len(ev) - whole
        if done:
            break
    if n_pending:
        yield Events.concatenate(pending)


def infer_sensor_size(max_x: float, max_y: float, source: str,
                      principal_point: tuple[float, float] | None = None) -> tuple[int, int]:
    """Smallest sensor of ``ti_cmax.camera.SENSORS`` (by pixel count) containing pixel (max_x, max_y) and,
    when a calibration gives it, whose central half holds the principal point (cx, cy): so a DAVIS240C
    recording whose first events happen to stay below x, y < 128 is not taken for a DVS128."""
    def centred(w, h):
        if principal_point is None:
            return True
        cx, cy = principal_point
        return abs(cx - w / 2) <= w / 4 and abs(cy - h / 2) <= h / 4

    fits = [(w * h, w, h) for (w, h) in SENSORS.values() if max_x < w and max_y < h and centred(w, h)]
    if not fits:
        raise InputError(
            f"cannot infer the sensor size (largest pixel x={max_x}, y={max_y}"
            + (f", principal point {principal_point}" if principal_point else "")
            + f" fits no known sensor "
            f"{sorted(SENSORS)}); give width and height (--set width=W --set height=H or a camera_info YAML)",
            source=source,
        )
    _, w, h = min(fits)
    return int(w), int(h)
