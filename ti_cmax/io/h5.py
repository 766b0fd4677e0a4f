"""Events in HDF5: our layout (writer + reader) and the common layouts of other tools (reader).

Layouts read (first match wins):
- ``events/{t,x,y,p}`` (ours; also DSEC / TUM-VIE): t float or integer, with an attribute ``units`` / ``unit``
  in {s, ms, us, ns} (a unit not known is refused); without it float is seconds and integer microseconds
  (CONVENTIONS.md); ``--set time_unit`` wins over both. Times read in that default unit are refused, naming the
  attribute to set, when their first events are too sparse for it (median gap >= 10 ms: microseconds stored as
  floats read as seconds, nanoseconds as microseconds) or their duration or event rate is beyond any recording
  (``_common.check_time_span``). float16 times, float times coarser than 0.1 ms at their largest value, and uint64
  times beyond 2^63 are refused. Polarity may be bool, integers, floats or strings (``events.polarity_signs``).
  A root dataset or attribute ``t_offset`` (microseconds, DSEC) is added. ``ms_to_idx`` (DSEC) speeds up seeking.
- ``events/{ts,xs,ys,ps}`` (E2VID-era): same time rules; root attribute ``sensor_resolution`` = (height, width).
- ``t,x,y,p`` at the root.
- ``CD/events`` (Prophesee Metavision HDF5): one compound dataset (x, y, p, t in microseconds); sensor size from
  the root attribute ``geometry`` ("1280x720"). Metavision compresses it with Prophesee's ECF codec (HDF5 filter
  0x8ECF), which no PyPI package provides: such a file opens when that plugin is installed (HDF5_PLUGIN_PATH),
  else it is refused at open with that advice; an uncompressed (or gzip) one always reads.
Sensor size comes from attributes ``width``/``height`` (root or ``events`` group), ``sensor_resolution`` or
``geometry``.
Intrinsics (``fx fy cx cy dist``), when our writer stored them, become the dataset's camera.
Data is always read in slices; a file compressed with a filter HDF5 lacks (Blosc, ZSTD, ...) gets ``import
hdf5plugin``, when installed, which registers them.
"""
from __future__ import annotations

import contextlib
import errno
import io
import os
from pathlib import Path
from typing import Iterator

import numpy as np

from ..camera import Camera
from ..errors import InputError
from ..events import ArrayPool, Events, polarity_signs, read_only_columns
from ._common import Block, check_time_span

import h5py

BLOCK_EVENTS = 2_000_000  # events per slice read (a multiple of the usual chunk sizes: no chunk straddles two)
_UNITS = {"s": 1.0, "sec": 1.0, "second": 1.0, "seconds": 1.0, "ms": 1e-3, "msec": 1e-3, "millisecond": 1e-3,
          "milliseconds": 1e-3, "us": 1e-6, "usec": 1e-6, "\u00b5s": 1e-6, "\u03bcs": 1e-6, "microsecond": 1e-6,
          "microseconds": 1e-6, "ns": 1e-9, "nsec": 1e-9, "nanosecond": 1e-9, "nanoseconds": 1e-9}
# float times without a unit are seconds, unless their first events are sparser than this median gap (s): under
# 100 events/s, not an event camera's seconds (microseconds stored as floats: a 1 s recording read as 11.6 days)
FLOAT_SECONDS_MAX_MEDIAN_GAP = 0.01
FLOAT_SECONDS_SAMPLE = 4096  # events at the start of the file that test it (at least 100 distinct times)
_LAYOUTS = (("events", ("t", "x", "y", "p")), ("events", ("ts", "xs", "ys", "ps")), ("", ("t", "x", "y", "p")))
MAX_TIME_STEP = 1e-4  # float times coarser than this (s) at their largest value are refused (float32 after ~1000 s)
_INT64_MAX = (1 << 63) - 1
METAVISION_EVENTS = "CD/events"
ECF_FILTER = 0x8ECF  # Prophesee's Event Compression Format, as an HDF5 filter id


def _open(path) -> h5py.File:
    try:
        return h5py.File(path, "r")
    except FileNotFoundError:
        raise InputError("file not found", source=str(path)) from None
    except OSError as exc:
        raise InputError(f"cannot open as HDF5 (truncated or not an HDF5 file): {exc}", source=str(path)) from None


def _need_filters(datasets) -> None:
    """Register hdf5plugin's compression filters (Blosc, ZSTD, LZ4, ...) with HDF5 when a dataset uses one that
    HDF5 lacks and hdf5plugin is installed. Imported only then: it costs ~0.05 s of every command's start-up."""
    for ds in datasets:
        plist = ds.id.get_create_plist()
        if not all(h5py.h5z.filter_avail(plist.get_filter(i)[0]) for i in range(plist.get_nfilters())):
            try:
                import hdf5plugin  # noqa: F401 - registers its filters
            except ImportError:  # reading fails with the advice to install it (H5Events._read_errors)
                pass
            return


def _geometry(value, source: str) -> tuple[int, int]:
    text = value.decode() if isinstance(value, bytes) else str(value)
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise InputError(f"attribute geometry={text!r}, expected WIDTHxHEIGHT", source=source) from None
    return w, h


def _attr(obj, *names):
    for n in names:
        if n in obj.attrs:
            v = obj.attrs[n]
            return v.decode() if isinstance(v, bytes) else v
    return None


class H5Events:
    """Read-only view of an events HDF5 file; opened per operation so no handle stays open."""

    def __init__(self, path, time_unit: str | None = None):
        self.path = Path(path)
        self.source = str(self.path)
        self.time_unit = time_unit or None  # the user's unit (--set time_unit): wins over the file's attribute
        with _open(self.path) as f:
            try:
                self._detect(f)
            except InputError:
                raise
            except (KeyError, OSError, ValueError) as exc:  # h5py's errors for damaged object headers
                raise InputError(f"cannot read the HDF5 structure (truncated or corrupt file): {exc}",
                                 source=self.source) from None

    def _columns(self, f: h5py.File) -> list:
        """The t, x, y, p columns as sliceable objects (datasets, or fields of the Metavision compound)."""
        if self.compound:
            ds = f[METAVISION_EVENTS]
            return [ds.fields(k) for k in ("t", "x", "y", "p")]
        return [f[n] for n in self._names]

    def _detect_metavision(self, f: h5py.File) -> bool:
        ds = f.get(METAVISION_EVENTS)
        if not isinstance(ds, h5py.Dataset) or ds.dtype.names is None:
            return False
        if not {"t", "x", "y", "p"} <= set(ds.dtype.names):
            raise InputError(f"{METAVISION_EVENTS} has fields {ds.dtype.names}, expected x, y, p, t", source=self.source)
        plist = ds.id.get_create_plist()
        if any(plist.get_filter(i)[0] == ECF_FILTER for i in range(plist.get_nfilters())) \
                and not h5py.h5z.filter_avail(ECF_FILTER):
            raise InputError("this Metavision HDF5 file is compressed with Prophesee's ECF codec, which is not "
                             "installed: install the hdf5_ecf plugin and set HDF5_PLUGIN_PATH, or record/convert "
                             "to RAW (.raw reads with pip install ti-cmax[prophesee])", source=self.source)
        self._names = [f"{METAVISION_EVENTS}/{k}" for k in ("t", "x", "y", "p")]
        return True

    def _detect(self, f: h5py.File):
        self.compound = self._detect_metavision(f)
        for group, names in _LAYOUTS:
            if self.compound:
                break
            if group and not isinstance(f.get(group), h5py.Group):
                continue
            g = f[group] if group else f
            if all(n in g and isinstance(g[n], h5py.Dataset) for n in names):
                self._names = [f"{group}/{n}" if group else n for n in names]
                break
        else:
            raise InputError("no events found: expected datasets events/{t,x,y,p}, events/{ts,xs,ys,ps} "
                             "or t,x,y,p at the root", source=self.source)
        dsets = self._columns(f)
        _need_filters([f[METAVISION_EVENTS]] if self.compound else dsets)
        lengths = {d.shape[0] if d.shape else -1 for d in dsets}
        if len(lengths) != 1 or any(len(d.shape) != 1 for d in dsets):
            raise InputError(f"event datasets {self._names} must be 1-D and of the same length", source=self.source)
        self.n = lengths.pop()
        tds = f[METAVISION_EVENTS] if self.compound else dsets[0]  # units attribute, if any
        is_float = np.issubdtype(dsets[0].dtype, np.floating)
        if not is_float and not np.issubdtype(dsets[0].dtype, np.integer):
            raise InputError(f"{self._names[0]} has dtype {dsets[0].dtype}, expected numbers", source=self.source)
        if dsets[0].dtype.itemsize < 4 and is_float:  # float16: steps of 0.5 ms at 1 s, 0.25 s at 1000 s
            raise InputError(f"{self._names[0]} holds {dsets[0].dtype} times, too coarse for event timestamps "
                             "(11-bit precision): store float64 seconds or integer microseconds", source=self.source)
        unit = self.time_unit or _attr(tds, "units", "unit")
        if unit is not None and str(unit).strip().lower() not in _UNITS:  # a float one was taken for seconds
            raise InputError(f"unknown time unit {unit!r} on {self._names[0]} (expected one of s, ms, us, ns)",
                             source=self.source)
        self.t_scale = _UNITS[str(unit).strip().lower()] if unit is not None else 1.0 if is_float else 1e-6
        self.unit_text = (f"read as {unit} (from --set time_unit)" if self.time_unit else
                          f"read as {unit} (its units attribute)" if unit is not None else
                          "read as seconds (float times without a units attribute)" if is_float else
                          "read as microseconds (integer times without a units attribute)")
        try:  # attributes written by other tools: one clear error for a malformed one
            off = 0
            if "t_offset" in f and isinstance(f["t_offset"], h5py.Dataset):
                off = int(np.asarray(f["t_offset"][()]).reshape(-1)[0])
            elif "t_offset" in f.attrs:
                off = int(np.asarray(f.attrs["t_offset"]).reshape(-1)[0])
            self.t_offset_raw = off  # same unit as the stored t
            self.has_ms_to_idx = "ms_to_idx" in f
            groups = [f] + ([f["events"]] if "events" in f and isinstance(f["events"], h5py.Group) else [])
            w = h = None
            for g in groups:
                if w is None and "width" in g.attrs and "height" in g.attrs:
                    w, h = int(g.attrs["width"]), int(g.attrs["height"])
                if w is None and "sensor_resolution" in g.attrs:
                    res = np.asarray(g.attrs["sensor_resolution"]).reshape(-1)
                    h, w = int(res[0]), int(res[1])
                if w is None and "geometry" in g.attrs:  # Metavision: "WIDTHxHEIGHT"
                    w, h = _geometry(g.attrs["geometry"], self.source)
            self.sensor_size = (w, h) if w is not None else None
            self.intrinsics = None
            for g in groups:
                if all(k in g.attrs for k in ("fx", "fy", "cx", "cy")):
                    dist = tuple(np.asarray(g.attrs["dist"], dtype=float).ravel()) if "dist" in g.attrs else ()
                    self.intrinsics = tuple(float(g.attrs[k]) for k in ("fx", "fy", "cx", "cy")) + (dist,)
                    break
        except (IndexError, ValueError, TypeError) as exc:
            raise InputError(f"malformed attribute (t_offset, width / height, sensor_resolution [h, w], geometry, "
                             f"fx fy cx cy dist): {type(exc).__name__}: {exc}", source=self.source) from None
        self.integer_xy = all(np.issubdtype(d.dtype, np.integer) for d in dsets[1:3])
        self._check_time_range(dsets[0], None if unit is not None else
                               "float times without a 'units' attribute, read as seconds" if is_float else
                               "integer times without a 'units' attribute, read as microseconds")

    def _fix(self) -> str:
        """What to set when the time unit is wrong."""
        return (f"set the attribute units on {self._names[0]} to their unit: 'us', 'ms' or 'ns' (or 's' to read them "
                "as seconds), or give it with --set time_unit=...")

    def _check_time_range(self, ds, default_unit: str | None) -> None:
        """Refuse float times too coarse for their range and, when read in a default unit (``default_unit`` says
        which; None: the file or the user states the unit), times whose first events are too sparse or whose duration
        or event rate is implausible in that unit."""
        if self.n == 0:
            return
        with self._read_errors():
            raw = np.concatenate([ds[0:1], ds[self.n - 1:self.n]])
            first, last = (float(v) for v in self._times(raw))
            if np.issubdtype(raw.dtype, np.floating):
                step = float(np.spacing(np.abs(raw).max().astype(raw.dtype))) * self.t_scale
                if step > MAX_TIME_STEP:
                    raise InputError(f"{self._names[0]} holds {raw.dtype} times whose resolution at "
                                     f"t={float(np.abs(raw).max())!r} is {step:.3g} s (coarser than "
                                     f"{MAX_TIME_STEP:g} s): store float64 seconds or integer microseconds",
                                     source=self.source)
            if default_unit is not None:  # a unit the file or the user states is taken as stated
                self._check_sparse(ds, default_unit)
                check_time_span(first, last, self.n, self.source, f"{self._names[0]} {self.unit_text}", self._fix())

    def _check_sparse(self, ds, what: str) -> None:
        """Times without a unit are read in a default one (CONVENTIONS.md); refuse them when the file's first events
        are too sparse for that (FLOAT_SECONDS_MAX_MEDIAN_GAP): e.g. microseconds stored as floats read as seconds, a 1 s recording as
        11.6 days at a few events per "second", without a word."""
        gaps = np.diff(self._times(np.asarray(ds[:min(self.n, FLOAT_SECONDS_SAMPLE)])))
        gaps = gaps[gaps > 0]
        if len(gaps) < 100:  # too few distinct times to tell
            return
        median = float(np.median(gaps))
        if median >= FLOAT_SECONDS_MAX_MEDIAN_GAP:
            raise InputError(f"{self._names[0]} holds {what}, but its first events are {median:.3g} s apart "
                             f"(median): too sparse for an event camera. {self._fix()[0].upper()}{self._fix()[1:]}",
                             source=self.source)

    # ------------------------------------------------------------------------------------------
    def _times(self, raw: np.ndarray, first: int = 0) -> np.ndarray:
        """Stored times (from event index ``first``) in seconds."""
        if np.issubdtype(raw.dtype, np.integer):
            if raw.dtype == np.uint64 and raw.size and int(raw.max()) > _INT64_MAX:  # would wrap to negative times
                i = int(np.argmax(raw > _INT64_MAX))
                raise InputError(f"{self._names[0]}: event {first + i} has time {int(raw[i])}, beyond any clock "
                                 f"(at most 2^63 - 1 = {_INT64_MAX})", source=self.source)
            return (raw.astype(np.int64) + self.t_offset_raw) * self.t_scale
        t = raw.astype(np.float64, copy=False)  # a fresh array from the read: the arithmetic may run in place
        if self.t_offset_raw:
            t += self.t_offset_raw
        if self.t_scale != 1:
            t *= self.t_scale
        return t

    def camera(self) -> Camera | None:
        if self.intrinsics is None or self.sensor_size is None:
            return None
        fx, fy, cx, cy, dist = self.intrinsics
        try:
            return Camera(self.sensor_size[0], self.sensor_size[1], fx, fy, cx, cy, dist)
        except InputError as exc:  # NaN or non-positive intrinsics in the attributes: name the file
            raise InputError(str(exc), source=self.source) from None

    def num_events(self) -> int:
        return self.n

    def time_range(self) -> tuple[float, float]:
        if self.n == 0:
            raise InputError("the file holds no events", source=self.source)
        with _open(self.path) as f, self._read_errors():
            ds = self._columns(f)[0]
            return float(self._times(ds[0:1])[0]), float(self._times(ds[self.n - 1:self.n])[0])

    @contextlib.contextmanager
    def _read_errors(self):
        try:
            yield
        except OSError as exc:
            raise InputError(f"cannot read events (truncated or corrupt HDF5, or a compression filter is "
                             f"missing: pip install hdf5plugin): {exc}", source=self.source) from None

    def _index_of_time(self, f, t: float) -> int:
        """First index with time >= t: binary search on single-element reads (data is sorted)."""
        ds = self._columns(f)[0]
        lo, hi = 0, self.n
        if self.has_ms_to_idx and self.t_scale == 1e-6:
            ms = np.asarray(f["ms_to_idx"][()])
            k = int(np.floor((t / 1e-6 - self.t_offset_raw) / 1000.0))
            if 0 <= k < len(ms):
                lo = int(ms[k])
            if 0 <= k + 1 < len(ms):
                hi = int(ms[k + 1])
        while lo < hi:
            mid = (lo + hi) // 2
            if self._times(ds[mid:mid + 1])[0] < t:
                lo = mid + 1
            else:
                hi = mid
        return lo

    def iter_blocks(self, block: int | None = None, t_start: float | None = None) -> Iterator[Block]:
        block = block or BLOCK_EVENTS
        with _open(self.path) as f, self._read_errors():
            dt, dx, dy, dp = self._columns(f)
            i = self._index_of_time(f, t_start) if t_start is not None else 0
            # start at a small margin before the cut so order across the border is still checked
            i = max(0, i - 1)
            # columns stored as they are used (float64 times, uint16 pixels, one-byte polarities) are read into
            # arrays reused from block to block (ArrayPool); the others into fresh ones, then converted
            pool = None if self.compound else ArrayPool((np.float64, np.uint16, np.uint16, np.int8), min(block, self.n))
            while i < self.n:
                j = min(i + block, self.n)
                cols = pool.take() if pool is not None else (None,) * 4
                t = self._times(_read(dt, i, j, cols[0]), i)
                x, y = (self._pixels(name, _read(ds, i, j, out), i)
                        for name, ds, out in zip(self._names[1:3], (dx, dy), cols[1:3]))
                p = cols[3]
                raw = _read(dp, i, j, None if p is None or dp.dtype.itemsize != 1 else p.view(dp.dtype))
                try:
                    p = polarity_signs(raw, f"{self._names[3]} (events {i}..{j - 1})",
                                       out=p[:j - i] if p is not None and np.shares_memory(raw, p) else None)
                except InputError as exc:
                    raise InputError(str(exc), source=self.source) from None
                if pool is not None:
                    pool.seal(cols)
                yield Block(read_only_columns(Events(t, x, y, p)), None, i)  # buffers may borrow them
                del t, x, y, p, raw, cols  # the next take() finds this set free once its views are gone
                i = j


    def _pixels(self, name: str, v: np.ndarray, first: int) -> np.ndarray:
        """Pixel coordinates read from ``name`` (events from index ``first``) as uint16, or float32 for sub-pixel
        ones; integers outside 0..65535 are refused (uint16 would wrap them)."""
        if not self.integer_xy:
            return v.astype(np.float32, copy=False)
        wide = v.dtype.itemsize > 2 or v.dtype.kind == "i"
        if wide and v.size and (v.min() < 0 or v.max() > 65535):
            k = int(np.argmax((v < 0) | (v > 65535)))
            raise InputError(f"{name}: event {first + k} has {name.rsplit('/', 1)[-1]}={int(v[k])}, outside the pixel "
                             "range 0..65535", source=self.source)
        return v.astype(np.uint16, copy=False)


def _read(ds, i: int, j: int, out: np.ndarray | None) -> np.ndarray:
    """Events i..j of the dataset ``ds``: into the first j - i rows of ``out`` when it has the dataset's dtype (no
    conversion), else a fresh array. A dataset stored in unfiltered chunks of native byte order is read chunk by chunk
    as stored (``read_direct_chunk``: none of HDF5's selection and conversion machinery, ~1.5 ns per event less)."""
    if out is None or out.dtype != ds.dtype:
        return ds[i:j]
    length = _raw_chunk_length(ds)
    if length:
        try:
            _read_chunks(ds, i, j, out, length)
            return out[:j - i]
        except (OSError, ValueError, KeyError):  # a chunk never written (fill value): HDF5 reads it
            pass
    ds.read_direct(out, np.s_[i:j], np.s_[0:j - i])
    return out[:j - i]


def _raw_chunk_length(ds) -> int:
    """Events per chunk of a 1-D dataset whose chunks hold the values as they are in memory (no filter, native byte
    order), else 0."""
    if ds.chunks is None or len(ds.chunks) != 1 or not ds.dtype.isnative or ds.dtype.kind not in "biuf" \
            or ds.id.get_create_plist().get_nfilters():
        return 0
    return int(ds.chunks[0])


def _read_chunks(ds, i: int, j: int, out: np.ndarray, length: int) -> None:
    """Events i..j of ``ds`` into ``out`` chunk by chunk; a chunk cut by i or j goes through a staging array."""
    staging = None
    for c in range(i - i % length, j, length):
        a, b = max(c, i), min(c + length, j)
        if a == c and b == c + length:
            ds.id.read_direct_chunk((c,), out=out[a - i:b - i].view(np.uint8))
        else:
            staging = np.empty(length, ds.dtype) if staging is None else staging
            ds.id.read_direct_chunk((c,), out=staging.view(np.uint8))
            out[a - i:b - i] = staging[a - c:b - c]


# ------------------------------------------------------------------------------------------------
class _GuardedFile(io.RawIOBase):
    """The file HDF5 writes through (h5py's file-object driver). HDF5 does not recover from a failed write: after a
    full disk (ENOSPC) or a file-size limit (EFBIG) the process crashed at exit (segmentation fault in the library's
    own clean-up). This file records the first failure and from then on discards writes, so HDF5 completes its
    close normally; the writer then raises the recorded error and the caller removes the file."""

    def __init__(self, path):
        self._f = open(path, "w+b", buffering=0)  # unbuffered: a seek never flushes (and fails) behind our back
        self.error: OSError | None = None

    def readable(self):
        return True

    def writable(self):
        return True

    def seekable(self):
        return True

    def seek(self, pos, whence=0):
        return self._f.seek(pos, whence)

    def tell(self):
        return self._f.tell()

    def readinto(self, b):
        return self._f.readinto(b)

    def write(self, b):
        view = memoryview(b).cast("B")
        if self.error is None:
            try:
                done = 0
                while done < len(view):
                    n = self._f.write(view[done:])
                    if not n:
                        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
                    done += n
                return done
            except OSError as exc:
                self.error = exc
        self._f.seek(len(view), os.SEEK_CUR)
        return len(view)

    def truncate(self, size=None):
        if self.error is None:
            try:
                return self._f.truncate(size)
            except OSError as exc:
                self.error = exc
        return size

    def flush(self):
        pass  # unbuffered

    def close(self):
        if not self._f.closed:
            try:
                self._f.close()
            except OSError as exc:
                self.error = self.error or exc
        super().close()

    def raise_error(self, path) -> None:
        """The recorded write failure, naming ``path``."""
        if self.error is not None:
            code = self.error.errno or errno.EIO
            raise OSError(code, os.strerror(code), str(path))


class EventsH5Writer:
    """Stream events into ``events/{t,x,y,p}`` (t float64 s, x/y uint16, p uint8 0/1), chunked and resizable.

    ``with EventsH5Writer(path, camera) as w: w.append(events)``; memory use is one appended batch.
    ``subpixel`` None: float32 x/y if the first batch has sub-pixel coordinates, else uint16.
    Sensor size (and intrinsics, when a camera is given) are stored as root attributes.
    """

    def __init__(self, path, camera: Camera | None = None, width: int | None = None, height: int | None = None,
                 chunk_events: int = 1 << 16, compression: str | None = None, subpixel: bool | None = None):
        self.path = Path(path)
        self.camera = camera
        self.width = camera.width if camera is not None else width
        self.height = camera.height if camera is not None else height
        self.chunk = int(chunk_events)
        self.compression = compression
        self.subpixel = subpixel
        self._f = None
        self._raw: _GuardedFile | None = None
        self.count = 0

    def __enter__(self):
        self._raw = _GuardedFile(self.path)
        f = self._f = h5py.File(self._raw, "w")
        if self.width is not None and self.height is not None:
            f.attrs["width"] = int(self.width)
            f.attrs["height"] = int(self.height)
        if self.camera is not None:
            for k in ("fx", "fy", "cx", "cy"):
                f.attrs[k] = float(getattr(self.camera, k))
            f.attrs["dist"] = np.asarray(self.camera.dist, dtype=float)
        return self

    def _create(self, subpixel: bool):
        """Datasets are made at the first append, so x/y get uint16 or (sub-pixel data) float32."""
        self.subpixel = bool(subpixel)
        g = self._f.create_group("events")
        xy = np.float32 if self.subpixel else np.uint16
        kw = dict(shape=(0,), maxshape=(None,), chunks=(self.chunk,), compression=self.compression)
        g.create_dataset("t", dtype=np.float64, **kw).attrs["units"] = "s"
        g.create_dataset("x", dtype=xy, **kw)
        g.create_dataset("y", dtype=xy, **kw)
        g.create_dataset("p", dtype=np.uint8, **kw)

    def append(self, events: Events):
        if self._f is None:
            raise RuntimeError("EventsH5Writer must be used as a context manager")
        n = len(events)
        if n == 0:
            return
        if "events" not in self._f:
            self._create(events.has_subpixel_coordinates if self.subpixel is None else self.subpixel)
        if events.has_subpixel_coordinates and not self.subpixel:
            raise InputError("sub-pixel events after integer ones: use EventsH5Writer(..., subpixel=True)")
        g = self._f["events"]
        i, j = self.count, self.count + n
        cols = {"t": events.t, "x": events.x, "y": events.y, "p": (events.p > 0).astype(np.uint8)}
        for k, v in cols.items():
            g[k].resize((j,))
            g[k][i:j] = v
        self.count = j
        self._raw.raise_error(self.path)  # a full disk ends the run here, not after the last event

    def close(self):
        """Close the file; raises the OSError of a write that failed (the file is then incomplete)."""
        if self._f is not None:
            try:
                if "events" not in self._f:
                    self._create(bool(self.subpixel))
                self._f.attrs["num_events"] = self.count
            finally:
                self._f.close()
                self._f = None
                self._raw.close()
            self._raw.raise_error(self.path)

    def __exit__(self, *exc):
        self.close()
        return False


def write_events_h5(path, events: Events, camera: Camera | None = None, width: int | None = None,
                    height: int | None = None, compression: str | None = None) -> Path:
    """Write all events to an HDF5 file in our layout (see EventsH5Writer)."""
    with EventsH5Writer(path, camera, width, height, compression=compression,
                        subpixel=events.has_subpixel_coordinates) as w:
        w.append(events)
    return Path(path)
