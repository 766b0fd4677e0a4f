"""Simulator rendering: sample an equirectangular log-intensity panorama through a rotating camera
and emit ESIM-like events from threshold crossings between closely spaced renders.

Two kernels per chunk of renders (the time stepping runs inside the kernels, one thread per pixel):

1. :func:`render_and_count` renders every pixel at all render times of the chunk into ``lbuf``
   (pixel-major, so each thread writes contiguously) and counts the events each pixel will emit.
2. After an exclusive prefix sum of the counts (numpy), :func:`write_events` replays the same
   crossing logic on ``lbuf`` and writes each event at its pixel's offset; it also advances the
   per-pixel state (reference log intensity, time of the last event).

Crossing model (ESIM): a pixel keeps a reference log intensity ``ref``. Between renders
(t0, L0) and (t1, L1), while ``L1 - ref >= c_pos`` (or ``ref - L1 >= c_neg``) the reference moves by
one threshold and an event is emitted at the time where the linear interpolation of L crosses the
new reference; that fraction of the render interval is clamped to [0, 1] (in float32 a change L1 - L0 of a few ulps
made it reach 4: an HD simulation had one event 9 us past its chunk's end, out of time order). With a refractory
period, an event closer than it to the pixel's previous emitted
event is dropped (the reference still moves, as in ESIM).

Panorama projection follows CONVENTIONS.md: lon = atan2(X, Z), lat = asin(Y/|X|),
u = w/2 + w lon/(2 pi), v = h/2 + h lat/pi, integer (u, v) = pixel centre, u wraps, v is clamped.
Everything here is float32 except timestamps (float64).

Numpy twins (:func:`render_numpy`, :func:`emit_numpy`) are the test oracles.
"""

import math  # (no `from __future__ import annotations`: Taichi needs evaluated annotations)

import numpy as np

from ti_cmax.kernels import bilinear
from ti_cmax.kernels.runtime import ensure_init, ti

_BL = bilinear.bilinear_funcs(ti.f32)

_F32_2 = ti.types.ndarray(dtype=ti.f32, ndim=2)
_F32_3 = ti.types.ndarray(dtype=ti.f32, ndim=3)
_F32_1 = ti.types.ndarray(dtype=ti.f32, ndim=1)
_F64_1 = ti.types.ndarray(dtype=ti.f64, ndim=1)
_I32_1 = ti.types.ndarray(dtype=ti.i32, ndim=1)
_I64_1 = ti.types.ndarray(dtype=ti.i64, ndim=1)
_U16_1 = ti.types.ndarray(dtype=ti.u16, ndim=1)
_I8_1 = ti.types.ndarray(dtype=ti.i8, ndim=1)

_TWO_PI = 2.0 * math.pi


@ti.func
def _atan_pos(x: ti.f32) -> ti.f32:
    """atan(x) for x >= 0 (Cephes atanf: range reduction + degree-9 odd polynomial, ~1e-7 rad).

    libm's atan2 + asin took 80 % of the render time on this machine; this is about 5x cheaper.
    """
    y = ti.f32(0.0)
    z = x
    if x > ti.f32(2.414213562373095):
        y = ti.f32(math.pi / 2)
        z = ti.f32(-1.0) / x
    elif x > ti.f32(0.4142135623730950):
        y = ti.f32(math.pi / 4)
        z = (x - ti.f32(1.0)) / (x + ti.f32(1.0))
    z2 = z * z
    p = ((ti.f32(8.05374449538e-2) * z2 - ti.f32(1.38776856032e-1)) * z2 + ti.f32(1.99777106478e-1)) * z2 \
        - ti.f32(3.33329491539e-1)
    return y + p * z2 * z + z


@ti.func
def _atan2(y: ti.f32, x: ti.f32) -> ti.f32:
    """atan2(y, x) in (-pi, pi] from :func:`_atan_pos`."""
    ay = ti.abs(y)
    ax = ti.abs(x)
    a = ti.f32(0.0)
    if ax > ti.f32(0.0):
        a = _atan_pos(ay / ax)
    elif ay > ti.f32(0.0):
        a = ti.f32(math.pi / 2)
    if x < ti.f32(0.0):
        a = ti.f32(math.pi) - a
    if y < ti.f32(0.0):
        a = -a
    return a


@ti.func
def _sample_pano(pano: ti.template(), dx: ti.f32, dy: ti.f32, dz: ti.f32) -> ti.f32:
    """Bilinear sample of the panorama along world direction (dx, dy, dz)."""
    h = pano.shape[0]
    w = pano.shape[1]
    lon = _atan2(dx, dz)
    lat = _atan2(dy, ti.sqrt(dx * dx + dz * dz))  # = asin(dy / |d|)
    u = ti.f32(0.5) * w + w * lon / ti.f32(_TWO_PI)
    v = ti.f32(0.5) * h + h * lat / ti.f32(math.pi)
    i0, j0, fu, fv = _BL.split(u, v)
    u0, u1 = _BL.wrap_cols(i0, w)  # i0 in [-1, w] up to round-off
    v0 = ti.min(ti.max(j0, 0), h - 1)  # rows clamped to the border (not dropped)
    v1 = ti.min(ti.max(j0 + 1, 0), h - 1)
    val, _, _ = _BL.interp(ti.Vector([pano[v0, u0], pano[v0, u1], pano[v1, u0], pano[v1, u1]]), fu, fv)
    return val


@ti.kernel
def _render_kernel(pano: _F32_2, bear: _F32_2, rot: _F32_2, out: _F32_1):
    for i in range(bear.shape[0]):
        bx, by, bz = bear[i, 0], bear[i, 1], bear[i, 2]
        dx = rot[0, 0] * bx + rot[0, 1] * by + rot[0, 2] * bz
        dy = rot[1, 0] * bx + rot[1, 1] * by + rot[1, 2] * bz
        dz = rot[2, 0] * bx + rot[2, 1] * by + rot[2, 2] * bz
        out[i] = _sample_pano(pano, dx, dy, dz)


@ti.kernel
def _render_count_kernel(
    pano: _F32_2, bear: _F32_2, rots: _F32_3, times: _F64_1, ref: _F32_1, cpos: _F32_1, cneg: _F32_1,
    last_t: _F64_1, refractory: ti.f64, lbuf: _F32_2, counts: _I32_1,
):
    nk = times.shape[0]
    for i in range(bear.shape[0]):
        bx, by, bz = bear[i, 0], bear[i, 1], bear[i, 2]
        r = ref[i]
        lt = last_t[i]
        cp = cpos[i]
        cn = cneg[i]
        cnt = 0
        lprev = ti.f32(0.0)
        for k in range(nk):
            dx = rots[k, 0, 0] * bx + rots[k, 0, 1] * by + rots[k, 0, 2] * bz
            dy = rots[k, 1, 0] * bx + rots[k, 1, 1] * by + rots[k, 1, 2] * bz
            dz = rots[k, 2, 0] * bx + rots[k, 2, 1] * by + rots[k, 2, 2] * bz
            lcur = _sample_pano(pano, dx, dy, dz)
            lbuf[i, k] = lcur
            if k > 0:
                t0 = times[k - 1]
                dt = times[k] - t0
                dl = lcur - lprev
                while lcur - r >= cp:
                    r += cp
                    te = t0 + dt * ti.cast(ti.min(ti.max((r - lprev) / dl, 0.0), 1.0), ti.f64)
                    if te - lt >= refractory:
                        cnt += 1
                        lt = te
                while r - lcur >= cn:
                    r -= cn
                    te = t0 + dt * ti.cast(ti.min(ti.max((r - lprev) / dl, 0.0), 1.0), ti.f64)
                    if te - lt >= refractory:
                        cnt += 1
                        lt = te
            lprev = lcur
        counts[i] = cnt


@ti.kernel
def _write_kernel(
    lbuf: _F32_2, times: _F64_1, ref: _F32_1, cpos: _F32_1, cneg: _F32_1, last_t: _F64_1,
    refractory: ti.f64, offsets: _I64_1, counts: _I32_1, width: ti.i32,
    out_t: _F64_1, out_x: _U16_1, out_y: _U16_1, out_p: _I8_1, written: _I32_1,
):
    nk = times.shape[0]
    for i in range(lbuf.shape[0]):
        r = ref[i]
        lt = last_t[i]
        cp = cpos[i]
        cn = cneg[i]
        cap = counts[i]
        base = offsets[i]
        xi = ti.cast(i % width, ti.u16)
        yi = ti.cast(i // width, ti.u16)
        j = 0
        lprev = lbuf[i, 0]
        for k in range(1, nk):
            lcur = lbuf[i, k]
            t0 = times[k - 1]
            dt = times[k] - t0
            dl = lcur - lprev
            while lcur - r >= cp:
                r += cp
                te = t0 + dt * ti.cast(ti.min(ti.max((r - lprev) / dl, 0.0), 1.0), ti.f64)
                if te - lt >= refractory:
                    lt = te
                    if j < cap:
                        out_t[base + j] = te
                        out_x[base + j] = xi
                        out_y[base + j] = yi
                        out_p[base + j] = ti.i8(1)
                        j += 1
            while r - lcur >= cn:
                r -= cn
                te = t0 + dt * ti.cast(ti.min(ti.max((r - lprev) / dl, 0.0), 1.0), ti.f64)
                if te - lt >= refractory:
                    lt = te
                    if j < cap:
                        out_t[base + j] = te
                        out_x[base + j] = xi
                        out_y[base + j] = yi
                        out_p[base + j] = ti.i8(-1)
                        j += 1
            lprev = lcur
        ref[i] = r
        last_t[i] = lt
        written[i] = j


# ------------------------------------------------------------------------------------------
# public wrappers
# ------------------------------------------------------------------------------------------

def _f32(a) -> np.ndarray:
    return np.ascontiguousarray(a, dtype=np.float32)


def render(pano: np.ndarray, bearings: np.ndarray, R: np.ndarray) -> np.ndarray:
    """Log intensity seen by each bearing (N, 3) (camera frame) under rotation R (world_from_camera)."""
    ensure_init()
    bear = _f32(bearings)
    out = np.empty(len(bear), np.float32)
    _render_kernel(_f32(pano), bear, _f32(R), out)
    return out


def render_and_count(pano, bearings, rots, times, ref, cpos, cneg, last_t, refractory: float):
    """Render all K+1 times of a chunk and count events per pixel.

    ``rots`` (K+1, 3, 3) at ``times`` (K+1,); times[0] is the previous chunk's last render
    (or the start). ``ref``, ``last_t`` are read only. Returns (lbuf (N, K+1) float32, counts int32).
    """
    ensure_init()
    n = len(bearings)
    times = np.ascontiguousarray(times, dtype=np.float64)
    lbuf = np.empty((n, len(times)), np.float32)
    counts = np.empty(n, np.int32)
    _render_count_kernel(_f32(pano), _f32(bearings), _f32(rots), times, ref, cpos, cneg, last_t,
                         float(refractory), lbuf, counts)
    return lbuf, counts


def write_events(lbuf, times, ref, cpos, cneg, last_t, refractory: float, counts, width: int):
    """Emit the events counted by :func:`render_and_count`, per pixel in time order (not globally
    sorted). Updates ``ref`` and ``last_t`` in place. Returns (t, x, y, p)."""
    ensure_init()
    counts = np.ascontiguousarray(counts, dtype=np.int32)
    offsets = np.zeros(len(counts), np.int64)
    np.cumsum(counts[:-1], out=offsets[1:])
    total = int(offsets[-1] + counts[-1]) if len(counts) else 0
    out_t = np.empty(total, np.float64)
    out_x = np.empty(total, np.uint16)
    out_y = np.empty(total, np.uint16)
    out_p = np.empty(total, np.int8)
    written = np.empty(len(counts), np.int32)
    _write_kernel(lbuf, np.ascontiguousarray(times, dtype=np.float64), ref, cpos, cneg, last_t,
                  float(refractory), offsets, counts, int(width), out_t, out_x, out_y, out_p, written)
    if not np.array_equal(written, counts):  # float contraction differences near a refractory limit
        keep = np.arange(total) - np.repeat(offsets, counts) < np.repeat(written, counts)
        out_t, out_x, out_y, out_p = out_t[keep], out_x[keep], out_y[keep], out_p[keep]
    return out_t, out_x, out_y, out_p


# ------------------------------------------------------------------------------------------
# numpy twins (test oracles)
# ------------------------------------------------------------------------------------------

def render_numpy(pano: np.ndarray, bearings: np.ndarray, R: np.ndarray) -> np.ndarray:
    """Numpy twin of :func:`render` (float64 math)."""
    pano = np.asarray(pano, dtype=np.float64)
    h, w = pano.shape
    d = np.asarray(bearings, dtype=np.float64) @ np.asarray(R, dtype=np.float64).T
    lon = np.arctan2(d[:, 0], d[:, 2])
    lat = np.arcsin(np.clip(d[:, 1] / np.linalg.norm(d, axis=1), -1, 1))
    u = w / 2 + w * lon / (2 * np.pi)
    v = h / 2 + h * lat / np.pi
    return bilinear.sample_numpy(pano, u, v, wrap_u=True, clamp_v=True)[0]


def emit_numpy(lbuf, times, ref, cpos, cneg, last_t, refractory: float, width: int):
    """Python twin of render_and_count + write_events on a given ``lbuf`` (small inputs only).

    Same arithmetic as the kernels (float32 log intensities and thresholds, float64 times), so the
    crossing decisions agree exactly. Returns (t, x, y, p, new_ref, new_last_t), pixel-major order.
    """
    f32 = np.float32
    lbuf = np.asarray(lbuf, dtype=f32)
    times = np.asarray(times, dtype=np.float64)
    ref = np.array(ref, dtype=f32)
    last_t = np.array(last_t, dtype=np.float64)
    ts, xs, ys, ps = [], [], [], []
    for i in range(lbuf.shape[0]):
        r, lt = f32(ref[i]), float(last_t[i])
        cp, cn = f32(cpos[i]), f32(cneg[i])
        for k in range(1, lbuf.shape[1]):
            l0, l1 = lbuf[i, k - 1], lbuf[i, k]
            t0, dt = times[k - 1], times[k] - times[k - 1]
            dl = f32(l1 - l0)
            for pol in (1, -1):
                while (l1 - r >= cp) if pol > 0 else (r - l1 >= cn):
                    r = f32(r + cp) if pol > 0 else f32(r - cn)
                    te = t0 + dt * min(max(float(f32(f32(r - l0) / dl)), 0.0), 1.0)
                    if te - lt >= refractory:
                        lt = te
                        ts.append(te), xs.append(i % width), ys.append(i // width), ps.append(pol)
        ref[i], last_t[i] = r, lt
    return (np.array(ts, np.float64), np.array(xs, np.uint16), np.array(ys, np.uint16),
            np.array(ps, np.int8), ref, last_t)


__all__ = ["render", "render_and_count", "write_events", "render_numpy", "emit_numpy"]
