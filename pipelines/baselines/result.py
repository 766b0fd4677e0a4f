"""What every baseline returns (trajectory, map, report) and the counted input stream they share."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ti_cmax.events import Events
from ti_cmax.trajectory import Trajectory

from ti_cmax.pipelines.frontend import as_chunks


@dataclass
class AngularVelocity:
    """Angular velocity estimates of a method that has them (written as angular_velocity.txt)."""

    t: np.ndarray  # (M,) s
    omega: np.ndarray  # (M, 3) rad/s, camera frame

    def __len__(self) -> int:
        return len(self.t)


@dataclass
class BaselineResult:
    """A baseline's trajectory, its own map (h, w) and report (status "ok" or "lost" with lost_at)."""

    trajectory: Trajectory
    map: np.ndarray
    report: dict
    frontend: AngularVelocity | None = None  # name kept from SlamResult: the slam writer reads it
    map_kind: str = "events"  # "events": counts of warped events; "intensity": 8-bit grayscale (SMT)


class CountedChunks:
    """The time-ordered chunks of an Events object, an iterable of chunks or a dataset, counting the events read
    (``count``), so that a baseline streams its input and still reports how much it consumed."""

    def __init__(self, events_or_chunks):
        self._chunks = as_chunks(events_or_chunks)
        self.span = _known_span(events_or_chunks)
        self.count = 0

    def __iter__(self):
        for chunk in self._chunks:
            self.count += len(chunk)
            yield chunk


def _known_span(events_or_chunks) -> float | None:
    """Duration of the input when it is known before reading (Events, dataset), for progress bars."""
    if isinstance(events_or_chunks, Events):
        return float(events_or_chunks.duration) if len(events_or_chunks) else None
    if hasattr(events_or_chunks, "time_range"):
        t0, t1 = events_or_chunks.time_range()
        return float(t1 - t0)
    return None


__all__ = ["AngularVelocity", "BaselineResult", "CountedChunks"]
