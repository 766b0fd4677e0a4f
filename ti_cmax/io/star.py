"""The star-tracking dataset's form (Chin et al., CVPRW 2019): undistorted floating-point events and a 3x3
calibration matrix.

Folder layout read and written here (``is_star_dataset`` recognizes it):

* ``events.txt``: one event per line, ``t x y p``: t in seconds, x/y floating-point coordinates that are
  already undistorted (they may fall slightly outside the sensor), p in {0, 1} or {-1, +1}; ``#`` comments.
* ``calibration.txt`` (also accepted: ``calib_matrix.txt``, or a ``calib.txt`` holding 3 rows of 3 numbers):
  a 3x3 matrix M, possibly a combined homography-calibration, that maps [x, y, 1] to a bearing direction
  ``M @ [x, y, 1]``; bearings are rescaled to the unit-depth plane (X/Z, Y/Z, 1) as the kernels expect.
* optional ``groundtruth.txt`` (TUM, R_world_from_camera) and ``sensor.txt`` (``width height``; default
  DAVIS240C 240x180, the sensor of the star dataset).

:class:`StarCamera` is a :class:`~ti_cmax.camera.Camera` whose ``bearings``/``unproject``/``project`` use M.
The front-end renders its IWEs with a pinhole K (fx, fy, cx, cy) fitted to M over the sensor (exact when
M^-1 is a pinhole matrix): any fixed smooth projection serves contrast maximisation, and the fit keeps the
warped events on an image the size of the sensor.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import Iterator

import numpy as np

from ..camera import Camera
from ..errors import InputError
from ..events import Events, signed_polarity
from ..outputs import OutputDir
from ..trajectory import Trajectory
from .events_txt import txt_time_range
from .text import read_tum, write_tum

CALIB_MATRIX_NAMES = ("calibration.txt", "calib_matrix.txt", "calib.txt")
DEFAULT_SENSOR = (240, 180)  # DAVIS240C
_BLOCK_BYTES = 8 << 20


# ------------------------------------------------------------------------------------------------
# camera
# ------------------------------------------------------------------------------------------------

def _pinhole_fit(matrix: np.ndarray, width: int, height: int) -> tuple[float, float, float, float]:
    """(fx, fy, cx, cy) such that fx X/Z + cx ~ x and fy Y/Z + cy ~ y over the sensor (least squares)."""
    ys, xs = np.mgrid[0:height:complex(0, 9), 0:width:complex(0, 9)]
    xs, ys = xs.ravel(), ys.ravel()
    b = np.column_stack([xs, ys, np.ones_like(xs)]) @ matrix.T
    if np.any(b[:, 2] <= 0):
        raise InputError("calibration matrix maps part of the sensor behind the camera (Z <= 0)")
    bx, by = b[:, 0] / b[:, 2], b[:, 1] / b[:, 2]
    ax = np.linalg.lstsq(np.column_stack([bx, np.ones_like(bx)]), xs, rcond=None)[0]
    ay = np.linalg.lstsq(np.column_stack([by, np.ones_like(by)]), ys, rcond=None)[0]
    return float(ax[0]), float(ay[0]), float(ax[1]), float(ay[1])


@dataclass(frozen=True)
class StarCamera(Camera):
    """Camera defined by a 3x3 matrix M mapping [x, y, 1] of (undistorted) event coordinates to bearings.

    Build with :meth:`from_matrix`; fx, fy, cx, cy are the pinhole fit of M (see module docstring).
    """

    matrix: tuple = field(default=())  # row-major 9 numbers

    def __post_init__(self):
        super().__post_init__()
        m = np.asarray(self.matrix, dtype=float).reshape(-1)
        if m.size != 9 or not np.isfinite(m).all():
            raise InputError("calibration matrix must hold 9 finite numbers (3x3)")
        if abs(np.linalg.det(m.reshape(3, 3))) < 1e-300:
            raise InputError("calibration matrix is singular")
        object.__setattr__(self, "matrix", tuple(float(v) for v in m))

    @classmethod
    def from_matrix(cls, matrix, width: int = DEFAULT_SENSOR[0], height: int = DEFAULT_SENSOR[1]) -> "StarCamera":
        m = np.asarray(matrix, dtype=float)
        if m.shape != (3, 3):
            raise InputError(f"calibration matrix must be 3x3, got shape {m.shape}")
        fx, fy, cx, cy = _pinhole_fit(m, int(width), int(height))
        if not (fx > 0 and fy > 0):
            # a mirrored matrix: flip is not representable by the pinhole fit
            raise InputError(f"calibration matrix gives a mirrored image (fitted fx={fx:.3g}, fy={fy:.3g})")
        return cls(int(width), int(height), fx, fy, cx, cy, (0.0,) * 5, tuple(m.ravel()))

    @property
    def M(self) -> np.ndarray:
        return np.asarray(self.matrix, dtype=float).reshape(3, 3)

    @cached_property
    def M_inv(self) -> np.ndarray:
        return np.linalg.inv(self.M)

    def unproject(self, x, y) -> np.ndarray:
        """Coordinates -> bearings (X/Z, Y/Z, 1) of M @ [x, y, 1], (N, 3) float64."""
        x = np.asarray(x, dtype=float)
        y = np.asarray(y, dtype=float)
        m = self.M
        z = m[2, 0] * x + m[2, 1] * y + m[2, 2]
        bx = (m[0, 0] * x + m[0, 1] * y + m[0, 2]) / z
        by = (m[1, 0] * x + m[1, 1] * y + m[1, 2]) / z
        return np.stack([bx, by, np.ones_like(bx)], axis=-1)

    def bearings(self, x, y, dtype=np.float32, columns: int = 3) -> np.ndarray:
        return self._unprojected(x, y, dtype, columns)

    def project(self, bearings, distort: bool = True) -> np.ndarray:
        """Bearings (N, 3) -> event coordinates (N, 2) through M^-1 (exact inverse of :meth:`unproject`)."""
        q = np.asarray(bearings, dtype=float) @ self.M_inv.T
        return np.stack([q[..., 0] / q[..., 2], q[..., 1] / q[..., 2]], axis=-1)

    def to_dict(self) -> dict:
        d = super().to_dict()
        d["matrix"] = [list(r) for r in self.M.tolist()]
        d["model"] = "3x3 calibration matrix (star dataset form); fx fy cx cy: pinhole fit used by the front-end"
        return d


# ------------------------------------------------------------------------------------------------
# reading
# ------------------------------------------------------------------------------------------------

def _numbers(path: Path) -> list[list[float]]:
    rows = []
    for i, raw in enumerate(path.read_text(encoding="utf-8", errors="replace").splitlines(), 1):
        line = raw.split("#", 1)[0].replace(",", " ").replace(";", " ").replace("[", " ").replace("]", " ")
        if not line.strip():
            continue
        try:
            rows.append([float(v) for v in line.split()])
        except ValueError:
            raise InputError(f"expected numbers, got {raw.strip()[:80]!r}", source=str(path), line=i) from None
    return rows


def _is_matrix_file(path: Path) -> bool:
    try:
        rows = _numbers(path)
    except (InputError, OSError):
        return False
    return len(rows) == 3 and all(len(r) == 3 for r in rows)


def find_calibration_matrix(folder) -> Path | None:
    """The 3x3 calibration file of a star-form folder, or None."""
    folder = Path(folder)
    for name in CALIB_MATRIX_NAMES:
        p = folder / name
        if p.is_file() and _is_matrix_file(p):
            return p
    return None


def is_star_dataset(path) -> bool:
    """True for a folder holding events.txt and a 3x3 calibration matrix file (or events.txt inside one)."""
    path = Path(path)
    folder = path if path.is_dir() else path.parent
    events = folder / "events.txt"
    if path.is_file() and path.suffix.lower() != ".txt":
        return False
    return events.is_file() and find_calibration_matrix(folder) is not None


def read_calibration_matrix(path) -> np.ndarray:
    path = Path(path)
    if not path.is_file():
        raise InputError("no such file", source=str(path))
    rows = _numbers(path)
    if not (len(rows) == 3 and all(len(r) == 3 for r in rows)):
        raise InputError(f"expected a 3x3 matrix (3 rows of 3 numbers), got rows of {[len(r) for r in rows]}",
                         source=str(path))
    return np.asarray(rows, dtype=float)


def _parse_exact(buf: bytes, first_line: int, source: str) -> tuple[np.ndarray, np.ndarray]:
    """Per-line parse (comments, odd spacing) with the offending line named on error: (n, 4) float64 and the line
    number of each row."""
    out, lines = [], []
    for i, raw in enumerate(buf.split(b"\n")):
        raw = raw.split(b"#", 1)[0]
        parts = raw.split()
        if not parts:
            continue
        if len(parts) != 4:
            raise InputError(f"expected 't x y p', got {len(parts)} values", source=source, line=first_line + i)
        try:
            out.append([float(v) for v in parts])
        except ValueError:
            raise InputError(f"expected numbers 't x y p', got {raw.decode(errors='replace')[:80]!r}",
                             source=source, line=first_line + i) from None
        lines.append(first_line + i)
    return np.asarray(out, dtype=float).reshape(-1, 4), np.asarray(lines, np.int64)


def _parse_block(buf: bytes, first_line: int, source: str) -> tuple[np.ndarray, np.ndarray]:
    if b"#" not in buf:
        lines = buf.count(b"\n")
        with np.errstate(all="ignore"):
            try:
                vals = np.array(buf.split(), dtype=float)  # C-level conversion of every token
            except ValueError:
                vals = None
        if vals is not None and vals.size == 4 * lines:
            return vals.reshape(-1, 4), first_line + np.arange(lines)
    return _parse_exact(buf, first_line, source)


def _check_rows(d: np.ndarray, lines: np.ndarray, prev_t: float, source: str, size: tuple[int, int] | None) -> None:
    """Finite values, sorted times, polarities 0/1 or -1/+1 and, with a sensor ``size``, coordinates within it
    extended by half its size on each side (undistorted coordinates may fall a little outside it; far outside,
    or beyond float32, they are not coordinates): one InputError naming the line and the value."""
    def fail(bad, message):
        i = int(np.argmax(bad))
        raise InputError(message(i), source=source, line=int(lines[i]))

    bad = ~np.isfinite(d).all(axis=1)
    if bad.any():
        fail(bad, lambda i: f"values must be finite numbers, got {' '.join(repr(float(v)) for v in d[i])}")
    t = d[:, 0]
    dec = np.diff(np.concatenate([[prev_t], t])) < 0
    if dec.any():
        fail(dec, lambda i: f"timestamps are not sorted: t={float(t[i])!r} comes after "
                            f"t={float(t[i - 1] if i else prev_t)!r}")
    bad = ~np.isin(d[:, 3], (0.0, 1.0, -1.0))
    if bad.any():
        fail(bad, lambda i: f"polarity must be 0/1 or -1/+1, got {float(d[i, 3])!r}")
    if size is not None:
        for k, name, n in ((1, "x", size[0]), (2, "y", size[1])):
            bad = (d[:, k] < -0.5 * n) | (d[:, k] > 1.5 * n)
            if bad.any():
                fail(bad, lambda i: f"{name}={float(d[i, k])!r} is far outside the {size[0]}x{size[1]} sensor "
                                    f"(expected {-0.5 * n:g} to {1.5 * n:g})")


def iter_star_events(path, chunk_bytes: int = _BLOCK_BYTES, sensor_size: tuple[int, int] | None = None
                     ) -> Iterator[Events]:
    """Stream ``t x y p`` lines with float coordinates as Events (x/y float32), validated (:func:`_check_rows`)."""
    path = Path(path)
    source = str(path)
    prev_t = -np.inf
    line = 1
    with open(path, "rb") as f:
        rest = b""
        while True:
            chunk = f.read(chunk_bytes)
            if not chunk and not rest:
                return
            buf = rest + chunk
            if chunk:
                k = buf.rfind(b"\n") + 1
                if k == 0:
                    rest = buf
                    continue
                buf, rest = buf[:k], buf[k:]
            else:
                buf, rest = buf + b"\n", b""
            d, lines = _parse_block(buf, line, source)
            if len(d):
                _check_rows(d, lines, prev_t, source, sensor_size)
                t = d[:, 0]
                prev_t = float(t[-1])
                yield Events(t, d[:, 1].astype(np.float32), d[:, 2].astype(np.float32),
                             signed_polarity(d[:, 3]))
            line += buf.count(b"\n")


def _rechunk(blocks: Iterator[Events], chunk_size: int, t_start, t_end) -> Iterator[Events]:
    pending: list[Events] = []
    n = 0
    for ev in blocks:
        if t_start is not None or t_end is not None:
            ev = ev.slice_time(-np.inf if t_start is None else t_start, np.inf if t_end is None else t_end)
        if len(ev):
            pending.append(ev)
            n += len(ev)
        while n >= chunk_size:
            allev = Events.concatenate(pending)
            yield allev[:chunk_size]
            pending = [allev[chunk_size:]]
            n -= chunk_size
    if n:
        yield Events.concatenate(pending)


class StarDataset:
    """A star-form folder opened with the same interface the commands use from ``ti_cmax.io.Dataset``."""

    format = "star text (float coordinates, 3x3 calibration)"

    def __init__(self, path, width: int | None = None, height: int | None = None):
        path = Path(path)
        if not path.exists():
            raise InputError("no such file or folder", source=str(path))
        folder = path if path.is_dir() else path.parent
        self.path = folder
        self.name = folder.name
        self.events_path = folder / "events.txt"
        if not self.events_path.is_file():
            raise InputError("no events.txt", source=str(folder))
        self.calib_path = find_calibration_matrix(folder)
        if self.calib_path is None:
            raise InputError(f"no 3x3 calibration matrix ({', '.join(CALIB_MATRIX_NAMES)})", source=str(folder))
        if width and height:
            self.width, self.height = int(width), int(height)
        elif (folder / "sensor.txt").is_file():
            rows = _numbers(folder / "sensor.txt")
            if not rows or len(rows[0]) != 2:
                raise InputError("expected 'width height'", source=str(folder / "sensor.txt"))
            self.width, self.height = int(rows[0][0]), int(rows[0][1])
        else:
            self.width, self.height = DEFAULT_SENSOR
        gt = folder / "groundtruth.txt"
        self.groundtruth_path = gt if gt.is_file() else None
        self.camera = StarCamera.from_matrix(read_calibration_matrix(self.calib_path), self.width, self.height)
        self.calibration_source = self.calib_path.name
        self.imu = None

    @cached_property
    def groundtruth(self) -> Trajectory | None:
        return read_tum(self.groundtruth_path) if self.groundtruth_path is not None else None

    def iter_events(self, chunk_size: int = 1_000_000, t_start: float | None = None,
                    t_end: float | None = None) -> Iterator[Events]:
        if chunk_size < 1:
            raise InputError(f"chunk_size must be >= 1, got {chunk_size}")
        return _rechunk(iter_star_events(self.events_path, sensor_size=(self.width, self.height)), int(chunk_size),
                        t_start, t_end)

    def read_events(self, t_start: float | None = None, t_end: float | None = None) -> Events:
        return Events.concatenate(list(self.iter_events(1 << 22, t_start, t_end)))

    @cached_property
    def _time_range(self) -> tuple[float, float]:
        return txt_time_range(self.events_path)

    def time_range(self) -> tuple[float, float]:
        return self._time_range

    def __repr__(self) -> str:
        return f"StarDataset({self.name!r}, {self.width}x{self.height})"


def open_star_dataset(path, width: int | None = None, height: int | None = None) -> StarDataset:
    return StarDataset(path, width, height)


# ------------------------------------------------------------------------------------------------
# writing
# ------------------------------------------------------------------------------------------------

def format_star_events(events: Events, decimals: int = 4) -> bytes:
    """Lines 't x y p' with t to the nanosecond, float coordinates, p in {0, 1}."""
    if len(events) == 0:
        return b""
    arr = np.column_stack([events.t, events.x.astype(np.float64), events.y.astype(np.float64),
                           (events.p > 0).astype(np.float64)])
    import io

    s = io.BytesIO()
    np.savetxt(s, arr, fmt=["%.9f", f"%.{decimals}f", f"%.{decimals}f", "%d"])
    return s.getvalue()


def write_star_dataset(folder, events, matrix, groundtruth: Trajectory | None = None,
                       sensor_size: tuple[int, int] | None = None, chunk: int = 500_000) -> Path:
    """Write a star-form folder (all-or-nothing): events.txt (from Events or an iterable of chunks),
    calibration.txt, sensor.txt and optional groundtruth.txt."""
    m = np.asarray(matrix, dtype=float)
    if m.shape != (3, 3):
        raise InputError(f"calibration matrix must be 3x3, got shape {m.shape}")
    chunks = [events] if isinstance(events, Events) else events
    with OutputDir(folder) as out:
        with open(out / "events.txt", "wb") as f:
            for ev in chunks:
                for i in range(0, len(ev), chunk):
                    f.write(format_star_events(ev[i:i + chunk]))
        np.savetxt(out / "calibration.txt", m, fmt="%.12g",
                   header="3x3 matrix M: bearing = M @ [x, y, 1] (event coordinates already undistorted)")
        if sensor_size is not None:
            (out / "sensor.txt").write_text(f"{int(sensor_size[0])} {int(sensor_size[1])}\n")
        if groundtruth is not None:
            write_tum(out / "groundtruth.txt", groundtruth)
    return Path(folder)


def undistorted_star_events(events: Events, camera: Camera, K_new: np.ndarray | None = None) -> Events:
    """Events of a (distorted, integer-pixel) camera -> the star form: undistorted float coordinates
    K_new @ bearing (K_new defaults to the camera's K), so that M = K_new^-1 maps them back to bearings."""
    K = camera.K if K_new is None else np.asarray(K_new, dtype=float)
    b = camera.bearings(events.x, events.y, dtype=np.float64)
    q = b @ K.T
    return Events(events.t, (q[:, 0] / q[:, 2]).astype(np.float32), (q[:, 1] / q[:, 2]).astype(np.float32),
                  events.p)


__all__ = [
    "StarCamera", "StarDataset", "open_star_dataset", "is_star_dataset", "read_calibration_matrix",
    "find_calibration_matrix", "iter_star_events", "write_star_dataset", "format_star_events",
    "undistorted_star_events", "CALIB_MATRIX_NAMES",
]
