"""Event times and pixel bearings gathered into a buffer in one pass, Taichi + numpy twin.

The back-end keeps every ``step``-th event as (t, bearing): the bearing is row y * width + x of the camera's
per-pixel table (float32 (h w, 3), as ``Camera.bearings`` looks it up), copied as is into column j of a (3, m) array
(one row per coordinate: the layout the back-end's kernels read, kernels/pano.py, so that a window's events reach
them by a row-wise copy, not a transposition); for an undistorted camera the
table's separable form (max(w, h), 3) serves: (lut[x, 0], lut[y, 1], lut[y, 2]), a few KB that stay in the
cache where the per-pixel table (3.7 MB on VGA, 11 MB on HD) misses it for most events. One kernel reads the events
where they are (a ring of capacity ``len(t)``: indices wrap) and writes straight into the caller's arrays, in place
of numpy's index arithmetic, ``take`` and the buffer's copies (one pass over the events instead of six).
"""
import numpy as np

from .runtime import BoundLaunch, ensure_init, ti

PARAMS = ("start", "step", "count", "width", "offset", "separable")  # the int64 slots of ``prm``


_F64_1 = ti.types.ndarray(dtype=ti.f64, ndim=1)
_U16_1 = ti.types.ndarray(dtype=ti.u16, ndim=1)
_F32_2 = ti.types.ndarray(dtype=ti.f32, ndim=2)
_I64_1 = ti.types.ndarray(dtype=ti.i64, ndim=1)


@ti.kernel
def _gather_kernel(t: _F64_1, x: _U16_1, y: _U16_1, lut: _F32_2, prm: _I64_1, out_t: _F64_1, out_b: _F32_2):
    """Row offset + j of out_t, column offset + j of out_b (3, m), from event i = start + j step, less len(t) past the
    end (start < len(t), (count - 1) step < len(t)), j < count."""
    start, step, count = ti.cast(prm[0], ti.i32), ti.cast(prm[1], ti.i32), ti.cast(prm[2], ti.i32)
    width, offset, separable = ti.cast(prm[3], ti.i32), ti.cast(prm[4], ti.i32), ti.cast(prm[5], ti.i32)
    capacity = t.shape[0]
    # on the calling thread: the loop is bound by memory, and a second thread adds more CPU time (waking and joining
    # it, contending for the same bandwidth: 6.2 against 4.4 ns per event for 25 000 events) than it saves
    ti.loop_config(serialize=True)
    for j in range(count):
        i = start + j * step
        if i >= capacity:
            i -= capacity
        row_x = ti.cast(x[i], ti.i32)
        row_y = ti.cast(y[i], ti.i32)
        if separable == 0:
            row_y = row_y * width + row_x
            row_x = row_y
        k = offset + j
        out_t[k] = t[i]
        out_b[0, k] = lut[row_x, 0]
        out_b[1, k] = lut[row_y, 1]
        out_b[2, k] = lut[row_y, 2]

def gather_numpy(t, x, y, lut, width: int, start: int, step: int, count: int, separable: bool = False) -> tuple:
    """Twin of the kernel (test oracle): the times and bearings (3, count) of events (start + j step) mod len(t),
    j < count."""
    i = (start + step * np.arange(count, dtype=np.int64)) % len(t)
    xi, yi = x[i].astype(np.int64), y[i].astype(np.int64)
    if separable:
        return t[i].copy(), np.stack([lut[xi, 0], lut[yi, 1], lut[yi, 2]])
    return t[i].copy(), np.ascontiguousarray(lut[yi * width + xi].T)


class BearingGather:
    """The kernel bound to a camera's table (``lut``, float32, C-contiguous: (height width, 3), or its separable form
    when ``separable``); a call rebinds only the arrays that moved (a bound launch costs ~2 us, a plain call ~100 us
    with seven arrays)."""

    def __init__(self, lut: np.ndarray, width: int, separable: bool = False):
        ensure_init()
        self._prm = np.zeros(len(PARAMS), np.int64)
        self._prm[3], self._prm[5] = width, bool(separable)
        self.lut = lut
        self._launch = None  # BoundLaunch, at the first call
        self._no_t, self._no_b = np.zeros(1), np.zeros((3, 1), np.float32)  # bound between calls
        self._keys: list = []

    @staticmethod
    def _key(a: np.ndarray) -> tuple:
        return a.ctypes.data, a.shape

    def __call__(self, t: np.ndarray, x: np.ndarray, y: np.ndarray, start: int, step: int, count: int,
                 out_t: np.ndarray, out_b: np.ndarray, offset: int) -> None:
        """Write events (start + j step) mod len(t), j < count, to row offset + j of ``out_t`` and column offset + j of
        ``out_b`` (t float64, x and y uint16 of the same length; out_t float64 (m,), out_b float32 (3, m), with
        room)."""
        if count <= 0:
            return
        if out_b.ndim != 2 or out_b.shape[0] != 3:
            raise ValueError(f"bearings go to a (3, m) array, not {out_b.shape}")
        if offset + count > len(out_t) or out_b.shape[1] < len(out_t):
            raise ValueError(f"{count} events at row {offset} do not fit {len(out_t)} rows")
        if (count - 1) * step >= len(t) or max(len(t), len(out_t), len(self.lut)) >= 2 ** 31:
            raise ValueError(f"{count} events of step {step} pass {len(t)} rows")
        self._prm[:3] = start % len(t), step, count
        self._prm[4] = offset
        arrays = (t, x, y, self.lut, self._prm, out_t, out_b)
        keys = [self._key(a) for a in arrays]
        if self._launch is None:
            self._launch = BoundLaunch(_gather_kernel, *arrays)
        else:
            for index, (key, old) in enumerate(zip(keys, self._keys)):
                if key != old:
                    self._launch.set_array(index, arrays[index])
        self._launch()
        # the output arrays are released (their owner may move its data in place when it alone holds them)
        self._launch.set_array(5, self._no_t)
        self._launch.set_array(6, self._no_b)
        self._keys = keys[:5] + [self._key(self._no_t), self._key(self._no_b)]

