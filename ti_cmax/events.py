"""The `Events` type: a struct of contiguous arrays.

t: float64 seconds (absolute, as in the file); x, y: pixel column/row (uint16, or float32 for
datasets that ship undistorted sub-pixel coordinates); p: polarity as int8 in {-1, +1}.
"""
from __future__ import annotations

import sys
from dataclasses import dataclass

import numpy as np

from .errors import InputError


_XY_DTYPES = (np.dtype(np.uint16), np.dtype(np.float32))


def _as(a, dtype) -> np.ndarray:
    return np.ascontiguousarray(a, dtype=dtype)


def signed_polarity(p: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
    """Polarities (0/1, -1/+1 or bool) as int8 {-1, +1}: p > 0 -> +1, else -1 (in int8 throughout: 1 ns per
    event instead of 8.5 for np.where's int64 temporary; reading is a real-time cost at 12 M ev/s). ``out``: the
    int8 array to write (it may be ``p``'s own memory: a reader's buffer), else a new one."""
    if out is None:
        out = np.empty(np.shape(p), np.int8)  # an array of its own (not a view of a bool one): buffers may borrow it
    np.greater(p, 0, out=out.view(bool))  # 0/1 bytes
    out += out  # in place: no temporaries
    out -= np.int8(1)
    return out


# polarity words of files that store it as text (HDF5 byte strings, CSV-like exports), lower case
_POSITIVE = frozenset(("1", "+1", "+", "1.0", "+1.0", "on", "true", "pos", "positive", "p"))
_NEGATIVE = frozenset(("0", "-1", "-", "0.0", "-1.0", "off", "false", "neg", "negative", "n"))


def polarity_word(text: str) -> int | None:
    """+1 or -1 for a polarity written as text (1/0, +1/-1, +/-, on/off, true/false, or a number equal to 1, 0 or
    -1 such as 1e0), else None."""
    word = text.strip().lower()
    if word in _POSITIVE or word in _NEGATIVE:
        return 1 if word in _POSITIVE else -1
    try:
        value = float(word)
    except ValueError:
        return None
    return 1 if value == 1 else -1 if value in (0, -1) else None


def polarity_signs(p, what: str = "polarity", out: np.ndarray | None = None) -> np.ndarray:
    """Polarities of any common dtype as int8 {-1, +1}, checked: bool; integers or floats in {-1, 0, 1} (0 and -1
    are negative); bytes or strings such as 1/0, +1/-1, +/-, on/off, true/false. Anything else (a 7, NaN, 'x', a
    compound) raises InputError naming ``what`` (the field and where) and the first offending value: p > 0 would
    have turned it into +1 without a word. ``out``: as for ``signed_polarity`` (numbers and bool)."""
    p = np.asarray(p)
    kind = p.dtype.kind
    if kind == "b":
        return signed_polarity(p, out)
    if kind in "iuf":
        if p.size and (kind == "f" or not ((kind == "u" or int(p.min()) >= -1) and int(p.max()) <= 1)):
            ok = (p == 0) | (p == 1) | (p == -1)
            if not ok.all():
                i = int(np.argmin(ok))
                raise InputError(f"{what}: value {p[i].item()!r} at position {i} is not a polarity "
                                 "(expected 0/1, -1/+1 or true/false)")
        return signed_polarity(p, out)
    if kind in "SUO":
        try:
            values, inverse = np.unique(p, return_inverse=True)
        except TypeError:  # an object array of mixed types
            values, inverse = None, None
        if values is not None:
            signs = np.zeros(len(values), np.int8)
            for k, v in enumerate(values.tolist()):
                text = v.decode("utf-8", "replace") if isinstance(v, bytes) else str(v)
                signs[k] = polarity_word(text) or 0
                if signs[k] == 0:
                    i = int(np.argmax(inverse.reshape(-1) == k))
                    raise InputError(f"{what}: value {text[:20]!r} at position {i} is not a polarity (expected "
                                     "1/0, +1/-1, +/-, on/off or true/false)")
            return signs[inverse.reshape(-1)]
    raise InputError(f"{what}: polarities of dtype {p.dtype} are not supported (expected bool, integers, floats or "
                     "strings such as 1/0, +/-)")


@dataclass(frozen=True, eq=False)
class Events:
    t: np.ndarray
    x: np.ndarray
    y: np.ndarray
    p: np.ndarray

    def __post_init__(self):
        t, x, y, p = self.t, self.x, self.y, self.p
        if type(t) is np.ndarray and type(x) is np.ndarray and type(y) is np.ndarray and type(p) is np.ndarray \
                and t.dtype == np.float64 and p.dtype == np.int8 and x.dtype == y.dtype \
                and x.dtype in _XY_DTYPES and t.ndim == 1 and len(x) == len(y) == len(p) == len(t) \
                and t.flags.c_contiguous and x.flags.c_contiguous and y.flags.c_contiguous and p.flags.c_contiguous:
            return  # already the columns of an Events (a slice, a view of a buffer): the checks below cost ~10 us
        n = len(self.t)
        if not (len(self.x) == len(self.y) == len(self.p) == n):
            raise InputError("events arrays t, x, y, p must have the same length")
        object.__setattr__(self, "t", _as(self.t, np.float64))
        xy_dtype = np.float32 if np.issubdtype(np.asarray(self.x).dtype, np.floating) else np.uint16
        object.__setattr__(self, "x", _as(self.x, xy_dtype))
        object.__setattr__(self, "y", _as(self.y, xy_dtype))
        p = np.asarray(self.p)
        if p.dtype != np.int8:
            p = polarity_signs(p)
        object.__setattr__(self, "p", _as(p, np.int8))

    # construction -------------------------------------------------------------------------
    @classmethod
    def empty(cls) -> "Events":
        return cls(np.zeros(0), np.zeros(0, np.uint16), np.zeros(0, np.uint16), np.zeros(0, np.int8))

    @classmethod
    def concatenate(cls, parts: list["Events"]) -> "Events":
        parts = [e for e in parts if len(e)]
        if not parts:
            return cls.empty()
        if len(parts) == 1:
            return parts[0]
        return cls(*(np.concatenate([getattr(e, f) for e in parts]) for f in ("t", "x", "y", "p")))

    # basic properties ---------------------------------------------------------------------
    def __len__(self) -> int:
        return len(self.t)

    @property
    def has_subpixel_coordinates(self) -> bool:
        return self.x.dtype == np.float32

    @property
    def duration(self) -> float:
        return float(self.t[-1] - self.t[0]) if len(self) > 1 else 0.0

    @property
    def nbytes(self) -> int:
        return sum(getattr(self, f).nbytes for f in ("t", "x", "y", "p"))

    # slicing ------------------------------------------------------------------------------
    def __getitem__(self, index) -> "Events":
        if isinstance(index, (int, np.integer)):
            index = slice(index, index + 1 if index != -1 else None)
        return Events(self.t[index], self.x[index], self.y[index], self.p[index])

    def index_at(self, t: float | np.ndarray, side: str = "left"):
        """Index of the first event with timestamp >= t (side='left') or > t (side='right')."""
        return np.searchsorted(self.t, t, side=side)

    def slice_time(self, t_start: float, t_end: float) -> "Events":
        """Events with t_start <= t < t_end (views, no copy)."""
        i0, i1 = self.index_at(t_start), self.index_at(t_end)
        return self[int(i0):int(i1)]

    def downsample(self, keep_one_of: int) -> "Events":
        """Keep one event out of Q (systematic, as the paper's event sampling rate)."""
        q = int(keep_one_of)
        if q < 1:
            raise InputError(f"event sample rate must be an integer >= 1, got {keep_one_of}")
        return self if q == 1 else self[::q]

    # validation ---------------------------------------------------------------------------
    def validate(self, width: int | None = None, height: int | None = None, source: str = "events") -> "Events":
        """Raise InputError on NaN/inf timestamps, decreasing timestamps or pixels outside the sensor."""
        if len(self) == 0:
            return self
        bad = ~np.isfinite(self.t)
        if bad.any():
            i = int(np.argmax(bad))
            raise InputError(f"event {i} has a non-finite timestamp ({float(self.t[i])})", source=source)
        dec = np.diff(self.t) < 0
        if dec.any():
            i = int(np.argmax(dec)) + 1
            raise InputError(
                f"timestamps are not sorted: event {i} at t={float(self.t[i])!r} comes after "
                f"t={float(self.t[i - 1])!r}",
                source=source,
            )
        if self.has_subpixel_coordinates:
            finite = np.isfinite(self.x) & np.isfinite(self.y)
            if not finite.all():
                i = int(np.argmin(finite))
                raise InputError(f"event {i} has a non-finite coordinate", source=source)
        for name, arr, limit in (("x", self.x, width), ("y", self.y, height)):
            if limit is None:
                continue
            out = (arr < 0) | (arr >= limit) if self.has_subpixel_coordinates else arr >= limit
            if out.any():
                i = int(np.argmax(out))
                raise InputError(
                    f"event {i} has {name}={arr[i]}, outside the sensor (expected 0 <= {name} < {limit})",
                    source=source,
                )
        return self

    def __repr__(self) -> str:
        if len(self) == 0:
            return "Events(n=0)"
        return f"Events(n={len(self)}, t=[{self.t[0]:.6f}, {self.t[-1]:.6f}] s)"


class EventBuffer:
    """A run of time-ordered events that grows at its end and drops its head cheaply: ``push`` appends, ``drop``
    moves a start index, and ``view()`` is an ``Events`` of views that stays valid: the buffer never writes where a
    view can look.

    Events whose columns are read-only views of larger arrays (a reader's blocks: ``read_only_columns``) are not
    copied: while the pushes follow each other in those arrays, the buffer is a range of them (it borrows them). Other
    events are copied into the buffer's own columns, which have spare room at the end (amortized growth); when the
    room runs out the live events move to the front of the same arrays if no view of them is alive, else to the
    spare ones (the arrays used before, reused once their views are gone), else to new arrays. A push that does not
    follow the borrowed range (the next block of a reader) is copied, with the live events; the buffer borrows again
    once every live event lies in the block the pushes go on in. A stream slicer joining its chunks by concatenation
    copies its whole buffer at each join instead; at high event rates that cost more than the rest of the slicing."""

    FIELDS = ("t", "x", "y", "p")

    def __init__(self):
        self._cols: tuple | None = None
        self._borrowed = False  # _cols are read-only arrays of the caller's (never written)
        self._spare: tuple | None = None  # own columns not in use (reused once no view is left)
        self._start = self._end = 0
        # own columns: their events from index ``at`` on are the copies of (arrays, index + delta) up to index end
        # of arrays (read-only), so the buffer can borrow those arrays again: (arrays, delta, at, end)
        self._copied_from: tuple | None = None

    def __len__(self) -> int:
        return self._end - self._start

    def push(self, events: Events) -> None:
        n = len(events)
        if not n:
            return
        new = [getattr(events, f) for f in self.FIELDS]
        origin = _origin(new)
        if origin is not None and self._borrow(origin, n):
            return
        self._copy(new, n)
        if origin is None:
            self._copied_from = None
            return
        arrays, index = origin
        run = self._copied_from
        if run is not None and _same(run[0], arrays) and run[3] == index:
            self._copied_from = (arrays, run[1], run[2], index + n)
        else:
            self._copied_from = (arrays, index - (self._end - n), self._end - n, index + n)

    def _borrow(self, origin: tuple, n: int) -> bool:
        """Take the ``n`` events at ``origin`` = (read-only arrays, index) as a range of those arrays, when that
        keeps the buffer one range: they follow the borrowed range, the buffer is empty, or its live events are
        copies of the events just before them in the same arrays."""
        arrays, index = origin
        if self._borrowed and _same(self._cols, arrays) and index == self._end:
            self._end += n
            return True
        run = self._copied_from
        if len(self):
            if self._borrowed or run is None or not _same(run[0], arrays) or run[3] != index \
                    or self._start < run[2]:
                return False
            start = self._start + run[1]
        else:
            start = index
        if not self._borrowed and self._cols is not None:
            self._spare = self._cols
        self._cols, self._borrowed, self._copied_from = tuple(arrays), True, None
        self._start, self._end = start, index + n
        return True

    def _copy(self, new: list, n: int) -> None:
        cols, live = self._cols, len(self)
        own = None if self._borrowed else cols
        same = cols is not None and cols[1].dtype == new[1].dtype
        if not (same and own is not None and self._end + n <= len(own[0])):
            # room to make: the live events move to the front of own arrays no view looks at, the current ones or
            # the spare ones (fresh arrays cost a page fault per 4 kB, more than the copy: a slicer whose last
            # packet is still looked at when the room runs out would otherwise allocate at every turn)
            target = None
            for candidate in (own, self._spare) if same else ():
                if candidate is not None and candidate[1].dtype == cols[1].dtype \
                        and 2 * (live + n) <= len(candidate[0]) and not viewed(candidate):
                    target = candidate
                    break
            if target is None:
                cap = max(3 * (live + n), 1024)  # room to move the live events to the front later (see above)
                old = cols if cols is not None else [np.zeros(0, c.dtype) for c in new]
                target = tuple(np.empty(cap, np.result_type(o.dtype, c.dtype)) for o, c in zip(old, new))
            if cols is not None:
                for dst, src in zip(target, cols):  # the live part is at most half: no overlap in place
                    dst[:live] = src[self._start:self._end]
            if target is self._spare:
                self._spare = own
            elif own is not None and target is not own:
                self._spare = own
            run = self._copied_from
            if run is not None and not self._borrowed:  # the own events moved by -start
                self._copied_from = (run[0], run[1] + self._start, run[2] - self._start, run[3])
            self._cols, self._borrowed, self._start, self._end = target, False, 0, live
        for dst, src in zip(self._cols, new):
            dst[self._end:self._end + n] = src
        self._end += n

    def drop(self, k: int) -> None:
        """Forget the first ``k`` events (at most all of them)."""
        self._start = min(self._end, self._start + max(0, int(k)))

    def view(self) -> Events:
        if self._cols is None or not len(self):
            return Events.empty()
        return Events(*(c[self._start:self._end] for c in self._cols))


def viewed(cols: tuple) -> bool:
    """Whether anything but the tuple ``cols`` (and this call) holds one of its arrays: a view, or a caller."""
    return any(sys.getrefcount(c) > 3 for c in cols)


class ArrayPool:
    """Sets of columns (one array per dtype of ``dtypes``, ``size`` rows each) that a reader fills block after block:
    ``take`` returns a set nothing else holds any more (made writeable again), else a new one, and keeps the last
    ``keep`` sets for reuse. Fresh arrays cost a page fault per 4 kB when written (a few us each in a virtual machine:
    more than the read itself at 12 M events/s); ``seal`` makes a filled set read-only, so buffers may borrow it
    (``EventBuffer``) and nothing writes it while it is looked at."""

    def __init__(self, dtypes, size: int, keep: int = 2):
        self.dtypes, self.size, self.keep = [np.dtype(d) for d in dtypes], int(size), int(keep)
        self._sets: list[tuple] = []

    def take(self) -> tuple:
        for cols in self._sets:
            if not viewed(cols):
                for c in cols:
                    c.flags.writeable = True
                return cols
        cols = tuple(np.empty(self.size, d) for d in self.dtypes)
        self._sets = [*self._sets[-(self.keep - 1):], cols] if self.keep > 1 else [cols]
        return cols

    @staticmethod
    def seal(cols: tuple) -> None:
        for c in cols:
            c.flags.writeable = False


def _same(a: tuple, b) -> bool:
    return all(u is v for u, v in zip(a, b))


def _origin(columns: list) -> tuple[tuple, int] | None:
    """(the arrays, the index) that the read-only, contiguous ``columns`` are views of, at the same index in each,
    or None (a writeable column: its owner may change it after the push)."""
    arrays, index = [], None
    for c in columns:
        base = c.base if c.base is not None else c
        if c.flags.writeable or type(base) is not np.ndarray or base.flags.writeable or base.dtype != c.dtype \
                or base.ndim != 1 or not base.flags.c_contiguous or c.strides[0] != c.itemsize:
            return None
        offset, rest = divmod(c.__array_interface__["data"][0] - base.__array_interface__["data"][0], c.itemsize)
        if rest or (index is not None and offset != index):
            return None
        arrays.append(base)
        index = offset
    return tuple(arrays), index


def read_only_columns(events: Events) -> Events:
    """``events`` with its columns made read-only (a reader's fresh block; nothing else holds them): the pipelines'
    buffers then take views of them instead of copies (``EventBuffer``)."""
    for f in EventBuffer.FIELDS:
        getattr(events, f).flags.writeable = False
    return events
