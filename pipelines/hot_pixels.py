"""Hot-pixel filter at the ingest of the pipelines: drops the events of pixels whose firing motion cannot explain.

Why: a hot (or flickering) pixel fires at a fixed sensor position whatever the camera does. Under a slow motion its
events pile up at a few image points, dominate the variance of every image of warped events and pull contrast
maximisation towards no motion (a still camera keeps them sharp).

Rule (isolation): a rotating camera moves brightness patterns across the sensor, so an edge or a point that makes a
pixel fire also crosses a neighbour of it: the next one along the motion (and, for an edge, those along the edge)
fires for the same pattern, as often up to the pixels' threshold mismatch. A pixel that fires far more than every
pixel around it is not seeing the scene. Over a block of events, with c the pixel's count and m the largest count
among its neighbours up to r = ``NEIGHBOURHOOD_RADIUS`` pixels away in x and y (24 of them), the pixel is hot when

    c >= hot_pixel_min_events   and   c >= hot_pixel_factor * (m + 1).

The rule compares counts of one block, so it holds from a DVS128 to an HD sensor and at any event rate without
scaling: the scene's rate moves c and m together. Polarity is ignored. Nothing depends on the events being even in
time, so a flickering pixel (bursts) is caught like a steadily hot one. ``hot_pixel_min_events`` (16) keeps noise
and the single events a faint edge gives one low-threshold pixel per crossing from being tested at all; the factor
(8) stands far above what threshold mismatch gives two pixels on the same edge (2 for a 30 % mismatch) and the
Poisson spread of small counts: on simulated sequences from a DVS128 to an HD sensor (0.4 to 33 M events/s; city,
bay and town scenes at up to 5 rad/s; star fields of 1000-3000 stars at 4-30 deg/s, also as undistorted star data)
the largest c / (m + 1) of a pixel that was not hot was 2.7 (over a 60 s pan, 138 blocks), while the 200 Hz hot
pixels of that pan's slow start scored 26-68 in its first 0.35 s. A star moving slowly (a sparse bright point)
passes from a pixel into the next: the pixel it leaves fires as much as the one it enters, so it is never isolated.
The radius of 2 covers undistorted star data, where neighbouring sensor pixels land up to 1.7 grid cells apart at the
image corners (DAVIS240C lens). Near the sensor's edge the neighbourhood is cut: a point entering the view fires the
first pixel it meets with no neighbour on the sensor, then moves on; a pixel within r of the edge must pass the rule
in two consecutive blocks. Two hot pixels side by side shield each other (a limit of the rule).

Blocks: the counts of the pixels not yet flagged build up until the busiest reaches ``BLOCK_PEAK_FACTOR`` (4) x
hot_pixel_min_events, where the factor can be met against neighbours with a few events, or the block holds
``BLOCK_EVENTS_PER_PIXEL`` (4) events per sensor pixel: then a pixel below that peak holds less than 64^2 / (16 P)
of the block's sum of squared counts (P pixels: 0.6 % on a DAVIS240C, 1.6 % on a DVS128), too little to pull an
image's variance. Then the rule runs and the counts restart. So blocks are short at high event rates and long at
low ones, where a slow hot pixel needs time to stand out, and a pixel that turns hot later is flagged at the end of
the block in which it does. Flagged pixels stay flagged: their later events are dropped before anything else sees
them. Events are counted as they come (one serial kernel pass drops the flagged pixels' events and counts the
others, a few ns per event); the block is checked once the events counted since the last check are an eighth of the
pixel count or span ``COUNT_INTERVAL`` s, so a block ends at most that late.

Start: the events are held back until the first test, which comes once the busiest pixel fired
``START_PEAK_FACTOR`` (2) x hot_pixel_min_events (hot pixels of similar rates then have hot_pixel_min_events each,
Poisson spread included), or the held events reach ``START_EVENTS_PER_PIXEL`` (1) per sensor pixel (a busy scene:
a pixel below 32 events then weighs under 1024 / P of the squared counts), or after ``hot_pixel_hold_time`` s of
sensor time; so the first packets and windows do not see the hot pixels of the start, when the motion is often
slowest. A 200 Hz hot pixel is caught within 0.2 s; a busy start is held about 0.05 s (1 M events/s on a
DAVIS240C). The held events are at most P events plus one count batch (13 bytes each: 0.6 MB on a DAVIS240C, 14 MB
on an HD sensor); besides, the filter keeps one count and one flag per pixel. Later events pass on as they come, less those of flagged pixels.
"""
from __future__ import annotations

from typing import Iterable, Iterator

import numpy as np

from ti_cmax.config import FrontendConfig
from ti_cmax.events import Events
from ti_cmax.kernels.pixel_count import PixelCounter

NEIGHBOURHOOD_RADIUS = 2  # neighbours up to 2 pixels away in x and y: 24 of them
BLOCK_PEAK_FACTOR = 4  # a block ends when its busiest pixel fired this x hot_pixel_min_events
BLOCK_EVENTS_PER_PIXEL = 4  # ... or holds this many events per sensor pixel
START_PEAK_FACTOR = 2  # the held start is tested when its busiest pixel fired this x hot_pixel_min_events
START_EVENTS_PER_PIXEL = 1  # ... or it holds this many events per sensor pixel
COUNT_INTERVAL = 0.02  # s of events at most between two checks of the block
REPORTED_PIXELS = 40  # coordinates listed in report.json at most


def neighbourhood_max(counts: np.ndarray, rows: np.ndarray, cols: np.ndarray, radius: int) -> np.ndarray:
    """The largest count among the (2 radius + 1)^2 - 1 neighbours of each pixel (rows, cols) of the 2-D ``counts``
    (pixels off the image count 0)."""
    height, width = counts.shape
    out = np.zeros(len(rows), counts.dtype)
    # pixels at least ``radius`` from the border (nearly all): neighbours read at flat offsets, no clipping
    inner = (rows >= radius) & (rows < height - radius) & (cols >= radius) & (cols < width - radius)
    flat, base = counts.ravel(), rows[inner] * width + cols[inner]
    part = out[inner]
    for dy in range(-radius, radius + 1):
        for dx in range(-radius, radius + 1):
            if dx or dy:
                np.maximum(part, flat[base + (dy * width + dx)], out=part)
    out[inner] = part
    rows, cols, border = rows[~inner], cols[~inner], np.zeros(np.count_nonzero(~inner), counts.dtype)
    for dy in range(-radius, radius + 1):
        for dx in range(-radius, radius + 1):
            if dx == 0 and dy == 0:
                continue
            r, c = rows + dy, cols + dx
            inside = (r >= 0) & (r < height) & (c >= 0) & (c < width)
            values = counts[np.clip(r, 0, height - 1), np.clip(c, 0, width - 1)]
            np.maximum(border, np.where(inside, values, 0), out=border)
    out[~inner] = border
    return out


def isolated_pixels(counts: np.ndarray, factor: float, min_events: int,
                    radius: int = NEIGHBOURHOOD_RADIUS) -> np.ndarray:
    """Flat indices of the pixels of the 2-D ``counts`` that the module's rule calls hot: at least ``min_events``
    and at least ``factor`` x (their largest neighbour's count + 1)."""
    flat = counts.ravel()
    candidates = np.flatnonzero(flat >= min_events)
    if len(candidates) == 0:
        return candidates
    # the largest neighbour count only grows with the neighbourhood: a candidate that fails against its nearest 8
    # neighbours fails against all of them, so the full neighbourhood is read only for those that pass (few: on a
    # VGA sensor the test of every candidate cost more per event than the counting)
    for r in sorted({min(1, radius), radius}):
        rows, cols = np.divmod(candidates, counts.shape[1])
        around = neighbourhood_max(counts, rows, cols, r)
        candidates = candidates[flat[candidates] >= factor * (around.astype(np.float64) + 1.0)]
    return candidates


class HotPixelFilter:
    """The module's filter over a time-ordered stream of event chunks on a ``width`` x ``height`` sensor.

    ``push(chunk)`` returns the chunks ready to go on (none while the start is held back), ``flush()`` those left at
    the end of the stream, ``filter(chunks)`` does both over an iterable. The decisions depend on the events alone,
    not on how the stream is cut into chunks. ``summary()`` is report.json's "hot_pixels" block. With
    ``hot_pixel_filter`` off every chunk passes unchanged.
    """

    def __init__(self, width: int, height: int, config: FrontendConfig = FrontendConfig()):
        self.width, self.height = int(width), int(height)
        self.enabled = bool(config.hot_pixel_filter)
        self.factor = float(config.hot_pixel_factor)
        self.min_events = int(config.hot_pixel_min_events)
        self.hold_time = float(config.hot_pixel_hold_time)
        pixels = self.width * self.height
        self.block_peak = BLOCK_PEAK_FACTOR * self.min_events
        self.start_peak = START_PEAK_FACTOR * self.min_events
        self.start_events = START_EVENTS_PER_PIXEL * pixels
        self.block_events = BLOCK_EVENTS_PER_PIXEL * pixels
        self._batch = max(1, pixels // 8)  # events counted between two checks of the block at most
        self.flagged = np.zeros(pixels, np.int8)  # nonzero: flagged (int8: the counting kernel's type)
        self._counts = np.zeros(pixels, np.int32)  # a block's counts (at most a few events per pixel on average)
        self._counter = PixelCounter(self.width, self.height, self._counts, self.flagged, self._batch) \
            if self.enabled else None
        self._in_block = 0  # events counted in the current block
        self._peak = 0  # the largest count in the current block
        self._pending_n = 0  # events counted since the last check of the block
        self._t_counted: float | None = None  # time of the last count
        self._holding = self.enabled
        self._suspects: set[int] = set()  # pixels near the edge that passed the rule in the last block
        self._held: list[Events] = []
        self._t_first: float | None = None
        self.events_seen = self.events_dropped = 0
        self.blocks = 0
        self.released_at: float | None = None  # sensor time at which the held start went on
        self.found: list[tuple[int, int, float, int]] = []  # (x, y, time flagged, count in its block)

    # ---- stream --------------------------------------------------------------------------------------------------
    def push(self, chunk: Events) -> list[Events]:
        """Take one chunk; return the chunks that may go on now (flagged pixels' events removed)."""
        if len(chunk) == 0:
            return []
        self.events_seen += len(chunk)
        if not self.enabled:
            return [chunk]
        if self._t_first is None:
            self._t_first = self._t_counted = float(chunk.t[0])
        t = chunk.t
        released: list[Events] = []
        parts: list[Events] = []  # what goes on directly
        first_out = None if self._holding else 0  # index of the first event that goes on directly
        dropped = 0
        i, n = 0, len(chunk)
        while i < n:
            if (self._pending_n >= self._batch or t[i] >= self._t_due()) and self._count(float(t[i])) \
                    and self._holding:
                released, first_out = self._release(), i
            j = max(i + 1, min(i + self._batch - self._pending_n, int(np.searchsorted(t, self._t_due(), "left"))))
            part = self._drop_and_count(chunk[i:j])
            dropped += j - i - len(part)
            if len(part):
                self._pending_n += len(part)
                if self._holding:  # a copy: a view would keep the caller's whole chunk alive
                    self._held.append(Events(*(np.array(getattr(part, f)) for f in ("t", "x", "y", "p"))))
                else:
                    parts.append(part)
            i = j
        if first_out is None:
            return []
        if dropped == 0:  # nothing dropped: the chunk itself (a view from where it goes on)
            direct = chunk if first_out == 0 else chunk[first_out:]
        else:
            direct = Events.concatenate(parts)
        return [e for e in (*released, direct) if len(e)]

    def flush(self) -> list[Events]:
        """End of the stream: count and test what the last block holds and release what is still held back."""
        if not self.enabled or self._t_counted is None:
            return []
        if self._pending_n:
            self._count(self._t_counted, end=True)
        if self._holding:
            if self._in_block:
                self._test(self._t_counted)
            return self._release()
        return []

    def filter(self, chunks: Iterable[Events]) -> Iterator[Events]:
        """The stream of ``chunks`` without the hot pixels' events (the start held back as ``push`` does)."""
        for chunk in chunks:
            yield from self.push(chunk)
        yield from self.flush()

    # ---- internals -----------------------------------------------------------------------------------------------
    def _t_due(self) -> float:
        """Time from which the pending events are counted (and, while holding, the start is tested)."""
        due = self._t_counted + COUNT_INTERVAL
        return min(due, self._t_first + self.hold_time) if self._holding else due

    def _pixel_index(self, chunk: Events) -> tuple[np.ndarray, np.ndarray | None]:
        """Flat pixel index of each event (int32: half the memory traffic of int64, which this per-event pass is
        bound by), and which events fall on the sensor (None: all). Sub-pixel coordinates (undistorted events) go to
        their nearest pixel; those off the sensor are neither counted nor dropped."""
        if not chunk.has_subpixel_coordinates:
            index = chunk.y.astype(np.int32)
            index *= self.width
            index += chunk.x
            return index, None
        x, y = np.rint(chunk.x).astype(np.int32), np.rint(chunk.y).astype(np.int32)
        inside = (x >= 0) & (x < self.width) & (y >= 0) & (y < self.height)
        return np.where(inside, y * self.width + x, 0), inside

    def _drop(self, chunk: Events) -> tuple[Events, np.ndarray, np.ndarray | None]:
        """``chunk`` without the events of flagged pixels, with their ``_pixel_index``."""
        index, inside = self._pixel_index(chunk)
        if not self.found or len(chunk) == 0:
            return chunk, index, inside
        hot = self.flagged[index].view(bool) if inside is None else self.flagged[index].view(bool) & inside
        if not hot.any():
            return chunk, index, inside
        self.events_dropped += int(np.count_nonzero(hot))
        keep = ~hot
        return chunk[keep], index[keep], None if inside is None else inside[keep]

    def _drop_and_count(self, chunk: Events) -> Events:
        """``chunk`` without the events of flagged pixels; the others added to the block's counts (events off the
        sensor, of sub-pixel coordinates, neither counted nor dropped)."""
        if chunk.has_subpixel_coordinates:
            chunk, index, inside = self._drop(chunk)
            index = index if inside is None else index[inside]
            if len(index):
                np.add.at(self._counts, index, np.int32(1))  # an int32 one: a Python 1 takes a slow cast path
                self._peak = max(self._peak, int(self._counts[index].max()))
                self._in_block += len(index)
            return chunk
        try:
            keep, peak, dropped = self._counter(chunk.x, chunk.y, bool(self.found))
        except ValueError:  # pixels off the sensor: the first one named
            chunk.validate(self.width, self.height, source="events")
            raise
        self._peak = max(self._peak, peak)
        self._in_block += len(chunk) - dropped
        if dropped:
            self.events_dropped += dropped
            return chunk[keep]
        return chunk

    def _count(self, t: float, end: bool = False) -> bool:
        """Check the block at sensor time t (its counts are up to date): test it when it is done (and say whether
        it was)."""
        self._pending_n = 0
        self._t_counted = t
        if end:
            return False
        if self._holding:
            done = self._peak >= self.start_peak or self._in_block >= self.start_events or \
                t >= self._t_first + self.hold_time
        else:
            done = self._peak >= self.block_peak or self._in_block >= self.block_events
        if done:
            self._test(t)
            return True
        return False

    def _test(self, t: float) -> None:
        """The module's rule over the block's counts; then a new block starts (and a held start goes on)."""
        counts = self._counts.reshape(self.height, self.width)
        hot = isolated_pixels(counts, self.factor, self.min_events)
        # near the sensor's edge the neighbourhood is cut: a point entering the view fires the first pixel it meets
        # with no neighbour on the sensor, then moves on; such a pixel must pass in two consecutive blocks
        y, x = np.divmod(hot, self.width)
        r = NEIGHBOURHOOD_RADIUS
        edge = (x < r) | (y < r) | (x >= self.width - r) | (y >= self.height - r)
        suspects, self._suspects = self._suspects, set(hot[edge].tolist())
        # membership in Python (few pixels): np.isin's first call imports a numpy module, 0.04 s of a 2 s recording
        hot = hot[~edge | np.array([int(i) in suspects for i in hot], bool)]
        for i in hot:
            y, x = divmod(int(i), self.width)
            self.found.append((x, y, t, int(self._counts[i])))
        self.flagged[hot] = 1
        self.blocks += 1
        self._counts[:] = 0
        self._in_block = self._peak = 0

    def _release(self) -> list[Events]:
        """The held start, without the events of the pixels flagged meanwhile; events go on as they come from now."""
        self._holding = False
        self.released_at = self._t_counted
        held, self._held = self._held, []
        kept = [part for part in (self._drop(part)[0] for part in held) if len(part)]
        return [Events.concatenate(kept)] if kept else []

    def all_dropped(self) -> str | None:
        """Why nothing went on when every event seen came from flagged pixels (one line), else None."""
        if not self.events_seen or self.events_dropped < self.events_seen:
            return None
        where = ", ".join(f"({x}, {y})" for x, y, _, _ in self.found[:5]) + (", ..." if len(self.found) > 5 else "")
        return (f"no events to process: all {self.events_seen} events came from {len(self.found)} hot pixel(s) "
                f"firing with no neighbour, {where} (hot_pixel_filter=false keeps them)")

    def summary(self) -> dict:
        """report.json's "hot_pixels" block: the pixels flagged (at most REPORTED_PIXELS listed, the first flagged
        first, with the sensor time and their count in the block that flagged them) and the events dropped."""
        return {
            "enabled": self.enabled,
            "count": len(self.found),
            "pixels": [[x, y] for x, y, _, _ in self.found[:REPORTED_PIXELS]],
            "flagged_at": [round(t, 6) for _, _, t, _ in self.found[:REPORTED_PIXELS]],
            "block_counts": [c for _, _, _, c in self.found[:REPORTED_PIXELS]],
            "events_dropped": int(self.events_dropped),
            "events_seen": int(self.events_seen),
            "blocks": int(self.blocks),
            "held_until": self.released_at,
        }


__all__ = ["HotPixelFilter", "isolated_pixels", "neighbourhood_max", "NEIGHBOURHOOD_RADIUS"]
