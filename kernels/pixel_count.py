"""Per-pixel event counting of the hot-pixel filter: one pass that drops the events of flagged pixels and counts the
others per pixel.

Why a kernel: in numpy the same step is four passes over the events (the flat pixel index, the flagged lookup,
``np.add.at``, a gather for the largest count), each a few ns per event, at every event the main process reads.
The loop is serial: it runs beside the front-end and a worker on few cores, and a serial count needs no atomics.

:func:`count_pixels_numpy` is the test oracle.
"""
import numpy as np

from ti_cmax.kernels.runtime import BoundLaunch, ensure_init, ti

_U16_1 = ti.types.ndarray(dtype=ti.u16, ndim=1)
_I32_1 = ti.types.ndarray(dtype=ti.i32, ndim=1)
_I8_1 = ti.types.ndarray(dtype=ti.i8, ndim=1)


# _count_kernel's parameter block (int32): inputs, then outputs
N, WIDTH, HEIGHT, ANY_FLAGGED, PEAK, DROPPED, OFF_SENSOR = range(7)


@ti.kernel
def _count_kernel(x: _U16_1, y: _U16_1, flagged: _I8_1, counts: _I32_1, keep: _I8_1, prm: _I32_1):
    """Events i < prm[N] on pixel y[i] * width + x[i]: keep[i] = 0 when the pixel is flagged (or off the sensor),
    else 1 and its count grows by one. Outputs: the largest count reached (0 if none), the events dropped, the
    events off the sensor. With prm[ANY_FLAGGED] = 0 nothing is dropped: neither ``flagged`` nor ``keep`` is
    touched."""
    n, width, height = prm[N], prm[WIDTH], prm[HEIGHT]
    peak = 0
    dropped = 0
    off = 0
    if prm[ANY_FLAGGED] == 0:
        ti.loop_config(serialize=True)
        for i in range(n):
            xi, yi = ti.cast(x[i], ti.i32), ti.cast(y[i], ti.i32)
            if xi < width and yi < height:
                k = yi * width + xi
                c = counts[k] + 1
                counts[k] = c
                peak = ti.max(peak, c)
            else:
                off += 1
    else:
        ti.loop_config(serialize=True)
        for i in range(n):
            xi, yi = ti.cast(x[i], ti.i32), ti.cast(y[i], ti.i32)
            if xi < width and yi < height:
                k = yi * width + xi
                kept = 1 - ti.cast(flagged[k] != 0, ti.i32)  # branch-free: the flagged pixels are unpredictable
                keep[i] = ti.cast(kept, ti.i8)
                dropped += 1 - kept
                c = counts[k] + kept
                counts[k] = c
                peak = ti.max(peak, c * kept)
            else:
                off += 1
                keep[i] = ti.i8(0)
    prm[PEAK] = peak
    prm[DROPPED] = dropped
    prm[OFF_SENSOR] = off


def count_pixels_numpy(x: np.ndarray, y: np.ndarray, width: int, flagged: np.ndarray,
                       counts: np.ndarray) -> tuple[np.ndarray, int, int]:
    """Twin of :class:`PixelCounter`'s call on events inside the sensor: (keep mask, largest count reached or 0,
    events dropped); ``counts`` grows in place."""
    index = y.astype(np.int64) * width + x
    keep = ~flagged[index].astype(bool)
    np.add.at(counts, index[keep], 1)
    peak = int(counts[index[keep]].max()) if keep.any() else 0
    return keep, peak, int(len(x) - np.count_nonzero(keep))


class PixelCounter:
    """Counts integer-pixel events into ``counts`` (int32, width x height, row-major) unless ``flagged`` (int8,
    same size, nonzero: flagged) marks their pixel. Both arrays are kept and updated in place. Chunks of at most
    ``capacity`` events go through staging arrays, so that the kernel stays bound to the same arrays (a bound
    launch costs ~2 us against ~60 us for a call, and rebinding an argument ~8 us)."""

    def __init__(self, width: int, height: int, counts: np.ndarray, flagged: np.ndarray, capacity: int):
        ensure_init()
        if counts.dtype != np.int32 or flagged.dtype != np.int8 or counts.shape != flagged.shape \
                or counts.size != width * height:
            raise TypeError("counts must be int32 and flagged int8, of width x height pixels")
        self.capacity = max(1, int(capacity))
        self._x, self._y = np.zeros(self.capacity, np.uint16), np.zeros(self.capacity, np.uint16)
        self._keep = np.ones(self.capacity, np.int8)
        self._prm = np.zeros(7, np.int32)
        self._prm[WIDTH], self._prm[HEIGHT] = width, height
        self._launch = BoundLaunch(_count_kernel, self._x, self._y, flagged, counts, self._keep, self._prm)

    def __call__(self, x: np.ndarray, y: np.ndarray, any_flagged: bool = True) -> tuple[np.ndarray | None, int, int]:
        """(keep mask: a view valid until the next call, None when no event was dropped; largest count reached or
        0; events dropped) for the events at columns ``x`` and rows ``y`` (uint16). ``any_flagged`` false: no pixel
        is flagged (the flags are not read). ValueError on events off the sensor (then some events were counted)."""
        n = len(x)
        if n > self.capacity:
            raise ValueError(f"{n} events: at most {self.capacity} per call")
        prm = self._prm
        prm[N], prm[ANY_FLAGGED] = n, bool(any_flagged)
        prm[PEAK:] = 0
        if n:
            self._x[:n] = x
            self._y[:n] = y
            self._launch()
        if prm[OFF_SENSOR]:
            raise ValueError(f"{int(prm[OFF_SENSOR])} events off the {prm[WIDTH]} x {prm[HEIGHT]} sensor")
        dropped = int(prm[DROPPED])
        return (self._keep[:n].view(bool) if dropped else None), int(prm[PEAK]), dropped


__all__ = ["PixelCounter", "count_pixels_numpy"]
