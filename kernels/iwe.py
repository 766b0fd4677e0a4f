"""Front-end image of warped events (IWE) for a constant angular velocity: contrast and its gradient.

One packet: bearings b_k on the unit-depth plane (undistorted, from ``Camera.bearings``) and relative
times dt_k = t_k - t_ref. Each bearing is rotated to t_ref by the exact rotation exp([omega]x dt_k)
(Rodrigues, not the first-order form), projected with K (pinhole, no distortion: the IWE lives on the
undistorted image plane) and voted bilinearly into a sensor-sized image I. Only in-bounds neighbours
receive votes, so an event leaving the image fades out continuously.

Contrast of the blurred image J = G * I, with G the Gaussian blur (sigma = frontend_blur_sigma) taken
over the whole plane (J keeps the mass that spills over the border), Np = width * height:

    mean_square:  C = ||J||^2 / Np
    variance:     C = ||J||^2 / Np - mu^2,   mu = sum(I) / Np

Because G is self-adjoint, ||J||^2 = <I, G2 I> with G2 = G^T G the blur by the self-convolved taps
g * g (zero padding on the sensor is then exact; the outer taps below 1e-5 of the centre are dropped: see
:func:`gram_taps`), and

    dC/domega = (2/Np) sum_k sum_{n in nbrs(k)} (H_n - mu) dw_kn/dpix . dpix_k/domega,  H = G2 I

(mu = 0 for the mean square). So one evaluation = two Taichi launches around one OpenCV blur:
  1. events (kernel ``vote``): warp, bilinear vote into I, sum of weights (-> mu). By default the event loops
             run on the calling thread (``IWEWorkspace`` docstring: why); with ``parts`` = P > 1 the events are
             split into P parts, each voting into its own copy of I with plain load/add/store: no float
             atomics (compare-and-swap loops on CPU) and a deterministic sum. The projection (u, v) is kept per
             event for pass 3;
  2. pixels: H = G2 (sum_p I_p), OpenCV's separable filter with zero padding (kernels/blur.py: SIMD; Taichi's
             CPU loops are scalar, and its 13-tap horizontal pass plus a 14-row gather per event cost more:
             per evaluation 1.0-1.1 -> 0.95-1.0 ms on 240 x 180, 2.6 -> 2.2-2.6 on 640 x 480, 5.4 -> 3.5 on
             1280 x 720, 20 000 events, 1 thread);
  3. events (kernel ``gather``): H at the four neighbours, then the cost term w.H and the gradient 3-vector
             from the warp (computed again), partial sums per group of 8 events (no gradient image). The cost alone
             (``with_grad=False``) skips it: <I, H> - mu sum(I) is one dot product of the two images.
Vectorisation: Taichi's CPU loops compile to LLVM loops that LLVM vectorises only when they store nothing to memory
it cannot tell apart from their inputs (a store to an ndarray or a field keeps them scalar). So passes 1 and 3 run
per block of _BLOCK events: the arithmetic (warp, projection; the gradient terms) in a loop whose results go to
local arrays (vectorised), then the scattered reads and writes of the image in a scalar loop. Warp and vote per
event cost 7 ns instead of 21, the gather 6-8 instead of 21 (HD packet of 76 000 events, 1 thread). The packet is
stored as rows (bx, by, bz, dt) of length N for the same reason (interleaved columns stay scalar), and a packet whose
angles |omega| max |dt_k| are all below 0.1 rad takes the Rodrigues series alone (sin is a library call, which keeps
a loop scalar).
Taichi 1.7.4's CPU range-for runs as tasks of >= 512 consecutive iterations, one thread each (see
kernels/runtime.py), so a loop over the 2 parts would run on one thread: pass 1 loops over PART_TASK iterations
per part (whole parts per task), pass 3 over event groups. Partial sums are stored per iteration and added in a
fixed order: a result does not depend on the schedule. The scalars of a launch travel in one small f64 ndarray
(an ndarray argument costs ~15-20 us of Python per launch, a scalar ~3).

d(exp(phi) b)/dphi = -[exp(phi) b]x Jl(phi) with phi = omega dt, so an event contributes
dt * Jl(phi)^T (x' x a), x' the rotated bearing and a = (dpix/dx')^T (dC/dpix).

Kernels are generated per dtype (f32 for speed, f64 for finite-difference checks) and sensor
size (compile-time constants); per-event buffers are fields allocated once per workspace, the images numpy arrays
(for OpenCV), the packet (4, N) an ndarray argument read in place. Kernel ``pack`` builds that packet from the
events' own arrays (1 of k events, table bearings plus dither, dt) in one launch (:meth:`IWEWorkspace.pack`).
:func:`contrast_numpy` and :func:`pack_numpy` are the float64 numpy twins (test oracles).
"""
import functools

import numpy as np

from ti_cmax.kernels import bilinear
from ti_cmax.kernels.bilinear import ADD, ATOMIC, bilinear_funcs
from ti_cmax.kernels.blur import gaussian_taps, separable_blur
from ti_cmax.kernels.runtime import PART_TASK, BoundLaunch, check_parts, ensure_init, num_threads, part_slice, ti

MEASURES = {"variance": 0, "mean_square": 1}
_DTYPES = {np.dtype(np.float32): "f32", np.dtype(np.float64): "f64"}
_GROUP = 8  # events per partial sum of pass 3 (in f32, then f64 in order)
_BLOCK = 64  # events per block of pass 1 and 3: a vectorised loop into local arrays, then the scalar reads/writes
SERIES_TH2 = 0.01  # below this squared angle the Rodrigues coefficients are their series (error < 1e-16)
SMALL_SLOT = 22  # prm slot: every angle of the packet at this omega is below sqrt(SERIES_TH2)


GRAM_TAP_FLOOR = 1e-5  # taps of g * g below this fraction of its centre are dropped


def gram_taps(sigma: float, truncate: float = 4.0) -> np.ndarray:
    """Taps of G^T G = g * g (length up to 4R+1), without the outer taps below ``GRAM_TAP_FLOOR`` of the centre:
    for sigma = 1 the radius drops from 8 to 6 (taps 4e-6 and 6e-8 of the centre; the cost changes by ~1e-5
    relative) and the blur and per-event gather passes cost 13/17 of the full taps."""
    g2 = np.convolve(gaussian_taps(sigma, truncate), gaussian_taps(sigma, truncate))
    cut = int(np.argmax(g2 >= GRAM_TAP_FLOOR * g2.max()))
    return g2[cut:len(g2) - cut]


def measure_id(measure: str) -> int:
    try:
        return MEASURES[measure]
    except KeyError:
        raise ValueError(f"unknown contrast measure {measure!r}; choose one of {sorted(MEASURES)}") from None


@functools.cache
def _build(dtype_name: str, height: int, width: int, capacity: int, parts: int, serial: bool):
    """Fields and kernels for one float type, sensor size, packet capacity and number of vote parts (compiled
    once). The images are ndarrays (numpy) so that OpenCV blurs them between the two kernels. ``serial`` (the
    default, and any build with one thread): the event loops run on the calling thread; a parallel loop is handed
    to Taichi's thread pool even with one thread, ~30-40 us per loop on these machines (a serial kernel launch
    costs ~12 us). The same sums in the same order (the compiled loop may round them differently: not bitwise the
    parallel build's)."""
    f = ti.f32 if dtype_name == "f32" else ti.f64
    bl = bilinear_funcs(f)
    h, w = height, width
    uv = ti.Vector.field(2, f, shape=capacity)  # pass 1 -> pass 3: u, v (u = -2: not in the image)
    out = ti.field(ti.f64, shape=8)
    psum = ti.Vector.field(2, ti.f64, shape=parts * PART_TASK)  # pass 1 partials: sum of weights, events landing
    gsum = ti.Vector.field(4, f, shape=(capacity + _GROUP - 1) // _GROUP)  # pass 3 partials per event group

    @ti.func
    def series(th2):
        """A = sin t / t, B = (1 - cos t)/t^2, C = (t - sin t)/t^3 by their 4-term series: truncation error
        < 1e-16 for t < 0.1 (th2 < SERIES_TH2)."""
        a = f(1.0) - th2 * f(1.0 / 6.0) * (f(1.0) - th2 * f(1.0 / 20.0) * (f(1.0) - th2 * f(1.0 / 42.0)))
        b = f(0.5) - th2 * f(1.0 / 24.0) * (f(1.0) - th2 * f(1.0 / 30.0) * (f(1.0) - th2 * f(1.0 / 56.0)))
        c = f(1.0 / 6.0) - th2 * f(1.0 / 120.0) * (f(1.0) - th2 * f(1.0 / 42.0) * (f(1.0) - th2 * f(1.0 / 72.0)))
        return a, b, c

    @ti.func
    def coeffs(th2):
        """A, B, C at any angle: the series below t = 0.1, else from sin (a library call: a loop using it stays
        scalar)."""
        a, b, c = series(th2)
        if th2 >= f(SERIES_TH2):
            th = ti.sqrt(th2)
            s = ti.sin(th)
            hs = ti.sin(f(0.5) * th)
            a = s / th
            b = f(2.0) * hs * hs / th2
            c = (th - s) / (th2 * th)
        return a, b, c

    @ti.func
    def warp(ev: ti.template(), k, wx, wy, wz, small: ti.template()):
        """Rotated bearing exp([w]x dt_k) b_k, phi = w dt_k, dt_k, B, C (ev: the packet, rows bx, by, bz, dt;
        ``small``: every |phi| of the packet is below 0.1, the series alone, a loop LLVM vectorises)."""
        bk = ti.Vector([ev[0, k], ev[1, k], ev[2, k]])
        dk = ev[3, k]
        phi = ti.Vector([wx * dk, wy * dk, wz * dk])
        th2 = phi.dot(phi)
        a, b, c = f(0.0), f(0.0), f(0.0)
        if ti.static(small):
            a, b, c = series(th2)
        else:
            a, b, c = coeffs(th2)
        pb = phi.cross(bk)
        xr = bk + a * pb + b * phi.cross(pb)
        return xr, phi, dk, b, c

    @ti.func
    def project(ev: ti.template(), k, wx, wy, wz, fx, fy, cx, cy, small: ti.template()):
        """Pixel (u, v) of event k warped at omega; u = -2 where it does not land in the image (behind the camera,
        or all four neighbours outside): branch-free, so that a loop of it vectorises."""
        xr, _phi, _dk, _b, _c = warp(ev, k, wx, wy, wz, small)
        front = xr[2] > f(1e-6)
        iz = f(1.0) / ti.select(front, xr[2], f(1.0))
        u = fx * xr[0] * iz + cx
        v = fy * xr[1] * iz + cy
        inside = front and u > f(-1.0) and v > f(-1.0) and u < f(float(w)) and v < f(float(h))
        return ti.select(inside, u, f(-2.0)), v

    @ti.kernel
    def vote(ev: ti.types.ndarray(dtype=f, ndim=2), img: ti.types.ndarray(dtype=f, ndim=2),
             prm: ti.types.ndarray(dtype=ti.f64, ndim=1)):
        """Pass 1: warp and vote (in-bounds neighbours only) into the zeroed copies of I in ``img``. Part p votes
        events [p*chunk, (p+1)*chunk) into its own copy (rows [p h, (p+1) h)) with plain load/add/store (float
        atomics are compare-and-swap loops on CPU); each CPU task holds whole parts (kernels/runtime.py), so one
        thread writes each copy, in event order (deterministic). Per block of _BLOCK events, the warp and
        projection run first into a local array (a loop without stores to memory, which LLVM vectorises), then
        the votes. Then mu's sums, serially in a fixed order. ``prm`` = n, omega (3), fx, fy, cx, cy, measure,
        with_grad, then the results (see gather), and at SMALL_SLOT whether the packet's angles are small (the
        series alone): an ndarray argument costs ~15-20 us of Python per launch, a scalar ~3."""
        n = ti.cast(prm[0], ti.i32)
        wx, wy, wz = ti.cast(prm[1], f), ti.cast(prm[2], f), ti.cast(prm[3], f)
        fx, fy, cx, cy = ti.cast(prm[4], f), ti.cast(prm[5], f), ti.cast(prm[6], f), ti.cast(prm[7], f)
        small = ti.cast(prm[SMALL_SLOT], ti.i32)
        ti.loop_config(serialize=serial)
        for it in range(parts * PART_TASK):
            part, k0, k1 = part_slice(it, n, parts)
            sw = f(0.0)
            cnt = 0
            kb = k0
            while kb < k1:
                m = ti.min(_BLOCK, k1 - kb)
                us = ti.Vector([f(0.0)] * _BLOCK)
                vs = ti.Vector([f(0.0)] * _BLOCK)
                xs = ti.Vector([0] * _BLOCK, ti.i32)
                ys = ti.Vector([0] * _BLOCK, ti.i32)
                axs = ti.Vector([f(0.0)] * _BLOCK)
                ays = ti.Vector([f(0.0)] * _BLOCK)
                for path in ti.static(range(2)):  # 0: small angles (the series alone), 1: any angle
                    if (small != 0) == (path == 0):
                        for j in range(m):
                            u, v = project(ev, kb + j, wx, wy, wz, fx, fy, cx, cy, path == 0)
                            us[j], vs[j] = u, v
                            xs[j], ys[j], axs[j], ays[j] = bl.split(u, v)
                for j in range(m):
                    u = us[j]
                    uv[kb + j] = ti.Vector([u, vs[j]])
                    if u > f(-1.0):
                        x0, y0, ax, ay = xs[j], ys[j], axs[j], ays[j]
                        if x0 >= 0 and y0 >= 0 and x0 < w - 1 and y0 < h - 1:  # all four neighbours inside
                            r = part * h + y0
                            bx = f(1.0) - ax
                            img[r, x0] = img[r, x0] + bx * (f(1.0) - ay)
                            img[r, x0 + 1] = img[r, x0 + 1] + ax * (f(1.0) - ay)
                            img[r + 1, x0] = img[r + 1, x0] + bx * ay
                            img[r + 1, x0 + 1] = img[r + 1, x0 + 1] + ax * ay
                            sw += f(1.0)
                        else:
                            sw += bl.scatter(img, part * h, h, y0, x0, x0 + 1, x0 >= 0, x0 + 1 < w, ax, ay, f(1.0),
                                             ADD)
                        cnt += 1
                kb += _BLOCK
            psum[it] = ti.Vector([ti.cast(sw, ti.f64), ti.cast(cnt, ti.f64)])
        ti.loop_config(serialize=True)
        for _ in range(1):
            acc1 = ti.Vector([0.0, 0.0], ti.f64)
            for it in range(parts * PART_TASK):
                acc1 += psum[it]
            out[0] = acc1[0]
            out[5] = acc1[1]
            prm[10] = acc1[0]
            prm[15] = acc1[1]

    @ti.func
    def gradient_term(ev: ti.template(), k, wx, wy, wz, fx, fy, gu, gv, small: ti.template()):
        """Event k's gradient term dt_k Jl(phi)^T (x' x a), a = (dpix/dx')^T (gu, gv): branch-free (0 where the
        event does not land: gu = gv = 0 there, and 1/z is finite)."""
        xr, phi, dk, b, c = warp(ev, k, wx, wy, wz, small)
        iz = f(1.0) / ti.select(xr[2] > f(1e-6), xr[2], f(1.0))
        av = ti.Vector([fx * gu * iz, fy * gv * iz, -(fx * gu * xr[0] + fy * gv * xr[1]) * iz * iz])
        cc = xr.cross(av)
        pc = phi.cross(cc)
        return dk * (cc - b * pc + c * phi.cross(pc))

    @ti.kernel
    def gather(ev: ti.types.ndarray(dtype=f, ndim=2), himg: ti.types.ndarray(dtype=f, ndim=2),
               prm: ti.types.ndarray(dtype=ti.f64, ndim=1)):
        """Pass 3: cost and gradient from H = G2 I at each event's four neighbours, per block of _BLOCK events: the
        neighbours' values first (scalar reads), then the gradient terms (the warp again: a vectorised loop costs
        less than storing it in pass 1 and reading it back), then the partial sums per group of _GROUP events in
        event order. prm[10:16] = sum of weights, cost term, gradient (3), events landing, prm[16:22] the sums of
        the products of the groups' gradient partials (xx, xy, xz, yy, yz, zz) (a kernel's vector return costs
        ~70 us of Python per launch)."""
        n = ti.cast(prm[0], ti.i32)
        wx, wy, wz = ti.cast(prm[1], f), ti.cast(prm[2], f), ti.cast(prm[3], f)
        fx, fy = ti.cast(prm[4], f), ti.cast(prm[5], f)
        measure = ti.cast(prm[8], ti.i32)
        with_grad = ti.cast(prm[9], ti.i32)
        small = ti.cast(prm[SMALL_SLOT], ti.i32)
        npix = f(float(h * w))
        mu = f(0.0)
        if measure == 0:
            mu = ti.cast(out[0], f) / npix
        ngroups = (n + _GROUP - 1) // _GROUP
        ti.loop_config(serialize=serial)
        for blk in range((n + _BLOCK - 1) // _BLOCK):
            kb = blk * _BLOCK
            m = ti.min(_BLOCK, n - kb)
            xs = ti.Vector([0] * _BLOCK, ti.i32)
            ys = ti.Vector([0] * _BLOCK, ti.i32)
            axs = ti.Vector([f(0.0)] * _BLOCK)
            ays = ti.Vector([f(0.0)] * _BLOCK)
            landed = ti.Vector([0] * _BLOCK, ti.i32)
            for j in range(m):
                q = uv[kb + j]
                landed[j] = ti.cast(q[0] > f(-1.0), ti.i32)  # landed in pass 1
                xs[j], ys[j], axs[j], ays[j] = bl.split(ti.max(q[0], f(-1.0)), q[1])
            h00 = ti.Vector([f(0.0)] * _BLOCK)
            h01 = ti.Vector([f(0.0)] * _BLOCK)
            h10 = ti.Vector([f(0.0)] * _BLOCK)
            h11 = ti.Vector([f(0.0)] * _BLOCK)
            for j in range(m):
                if landed[j] != 0:
                    x0, y0 = xs[j], ys[j]
                    if x0 >= 0 and y0 >= 0 and x0 < w - 1 and y0 < h - 1:  # all four neighbours inside
                        h00[j], h01[j] = himg[y0, x0] - mu, himg[y0, x0 + 1] - mu
                        h10[j], h11[j] = himg[y0 + 1, x0] - mu, himg[y0 + 1, x0 + 1] - mu
                    else:
                        oka, okb = bl.col_ok(x0, w)
                        hv = bl.gather(himg, 0, h, y0, x0, x0 + 1, oka, okb, -1)
                        # neighbours outside the image are dropped (weight 0), the others carry H - mu'
                        for dj, di in ti.static(ti.ndrange(2, 2)):
                            yy = y0 + dj
                            keep = yy >= 0 and yy < h and (oka if di == 0 else okb)
                            hv[2 * dj + di] = f(keep) * (hv[2 * dj + di] - mu)
                        h00[j], h01[j], h10[j], h11[j] = hv[0], hv[1], hv[2], hv[3]
            ws = ti.Vector([f(0.0)] * _BLOCK)
            gus = ti.Vector([f(0.0)] * _BLOCK)
            gvs = ti.Vector([f(0.0)] * _BLOCK)
            for j in range(m):
                # cost term sum_n w_n (H_n - mu'): sums to <I, G2 I> - mu' sum(I) = C * Np
                ws[j], gus[j], gvs[j] = bl.interp(ti.Vector([h00[j], h01[j], h10[j], h11[j]]), axs[j], ays[j])
            gx = ti.Vector([f(0.0)] * _BLOCK)
            gy = ti.Vector([f(0.0)] * _BLOCK)
            gz = ti.Vector([f(0.0)] * _BLOCK)
            if with_grad != 0:
                for path in ti.static(range(2)):
                    if (small != 0) == (path == 0):
                        for j in range(m):
                            gk = gradient_term(ev, kb + j, wx, wy, wz, fx, fy, gus[j], gvs[j], path == 0)
                            gx[j], gy[j], gz[j] = gk[0], gk[1], gk[2]
            for g in range((m + _GROUP - 1) // _GROUP):
                acc = ti.Vector([f(0.0), f(0.0), f(0.0), f(0.0)])
                for j in range(g * _GROUP, ti.min(m, (g + 1) * _GROUP)):
                    acc += ti.Vector([gx[j], gy[j], gz[j], ws[j]])
                gsum[blk * (_BLOCK // _GROUP) + g] = acc
        # f64 sums of the group partials, in order, and of the products of their gradient parts (the gradient's
        # noise: IWEWorkspace.gradient_covariance)
        ti.loop_config(serialize=True)
        for _ in range(1):
            acc3 = ti.Vector([0.0, 0.0, 0.0, 0.0], ti.f64)
            sq = ti.Vector([0.0, 0.0, 0.0, 0.0, 0.0, 0.0], ti.f64)
            for grp in range(ngroups):
                p = ti.cast(gsum[grp], ti.f64)
                acc3 += p
                sq += ti.Vector([p[0] * p[0], p[0] * p[1], p[0] * p[2], p[1] * p[1], p[1] * p[2], p[2] * p[2]])
            for q in ti.static(range(6)):
                prm[16 + q] = sq[q]
            out[2] = acc3[0]
            out[3] = acc3[1]
            out[4] = acc3[2]
            out[1] = acc3[3]
            for q in range(6):  # in the serial block: a loop of its own would be one more thread-pool task
                prm[10 + q] = out[q]

    @ti.kernel
    def render(ev: ti.types.ndarray(dtype=f, ndim=2), n: ti.i32, wx: f, wy: f, wz: f, fx: f, fy: f, cx: f, cy: f,
               dst: ti.types.ndarray(dtype=f, ndim=2)):
        """Unblurred IWE I into dst (h, w) (zeroed here), for display and tests."""
        for i, j in ti.ndrange(h, w):
            dst[i, j] = f(0.0)
        for k in range(n):
            xr, _phi, _dk, _b, _c = warp(ev, k, wx, wy, wz, False)
            if xr[2] > f(1e-6):
                u = fx * xr[0] / xr[2] + cx
                v = fy * xr[1] / xr[2] + cy
                if u > f(-1.0) and v > f(-1.0) and u < f(float(w)) and v < f(float(h)):
                    bl.vote(dst, u, v, f(1.0), ATOMIC)

    return vote, gather, render


@functools.cache
def _pack_kernel(dtype_name: str):
    """Kernel ``pack``: a packet's rows (bearing from the per-pixel table, plus dither; dt) from the events' own
    arrays, read in place (see :meth:`IWEWorkspace.pack`)."""
    f = ti.f32 if dtype_name == "f32" else ti.f64

    @ti.kernel
    def pack(t: ti.types.ndarray(dtype=ti.f64, ndim=1), x: ti.types.ndarray(dtype=ti.u16, ndim=1),
             y: ti.types.ndarray(dtype=ti.u16, ndim=1), lut: ti.types.ndarray(dtype=f, ndim=2),
             dxy: ti.types.ndarray(dtype=f, ndim=2), out: ti.types.ndarray(dtype=f, ndim=2),
             prm: ti.types.ndarray(dtype=ti.f64, ndim=1)):
        """Column j of ``out`` (rows bx, by, bz, dt) from event i = start + j step (j < n): lut[y_i w + x_i] (bx, by,
        bz) + (dx, dy) of dither row offset + j (when dithered), and dt = t_i - t_ref rounded to the workspace's
        float; prm = start, step, n, t_ref, sensor width, dithered, dither offset, then max |dt| (out), then
        separable: the table is (lut[x_i, 0], lut[y_i, 1], lut[y_i, 2]) (an undistorted camera: see
        :meth:`IWEWorkspace.pack`), then grid step g (> 0, a power of 2: the table is a grid of nodes every g
        pixels, rows of prm[10] nodes, interpolated bilinearly; see :meth:`IWEWorkspace.pack`)."""
        start = ti.cast(prm[0], ti.i64)
        step = ti.cast(prm[1], ti.i64)
        n = ti.cast(prm[2], ti.i32)
        t_ref = prm[3]
        width = ti.cast(prm[4], ti.i32)
        dithered = ti.cast(prm[5], ti.i32)
        offset = ti.cast(prm[6], ti.i32)
        separable = ti.cast(prm[8], ti.i32)
        g = ti.cast(prm[9], ti.i32)
        gw = ti.cast(prm[10], ti.i32)
        gshift = 0
        while (1 << gshift) < g:
            gshift += 1
        ginv = f(1.0) / ti.cast(ti.max(g, 1), f)
        ti.loop_config(serialize=True)
        for _ in range(1):
            big = f(0.0)
            for j in range(n):
                i = start + j * step
                xi = ti.cast(x[i], ti.i32)
                yi = ti.cast(y[i], ti.i32)
                row_x = yi * width + xi
                row_y = row_x
                if separable != 0:
                    row_x = xi
                    row_y = yi
                bx = lut[row_x, 0]
                by = lut[row_y, 1]
                bz = lut[row_y, 2]
                if g > 0:  # bilinear between the grid nodes around the pixel
                    gx = xi >> gshift  # g = 2^gshift: a shift, not an integer division
                    gy = yi >> gshift
                    ax = ti.cast(xi & (g - 1), f) * ginv
                    ay = ti.cast(yi & (g - 1), f) * ginv
                    r = gy * gw + gx
                    bx = (f(1.0) - ay) * ((f(1.0) - ax) * lut[r, 0] + ax * lut[r + 1, 0]) \
                        + ay * ((f(1.0) - ax) * lut[r + gw, 0] + ax * lut[r + gw + 1, 0])
                    by = (f(1.0) - ay) * ((f(1.0) - ax) * lut[r, 1] + ax * lut[r + 1, 1]) \
                        + ay * ((f(1.0) - ax) * lut[r + gw, 1] + ax * lut[r + gw + 1, 1])
                    bz = lut[r, 2]
                if dithered != 0:
                    bx += dxy[offset + j, 0]
                    by += dxy[offset + j, 1]
                d = ti.cast(t[i] - t_ref, f)
                out[0, j] = bx
                out[1, j] = by
                out[2, j] = bz
                out[3, j] = d
                big = ti.max(big, ti.abs(d))
            prm[7] = ti.cast(big, ti.f64)

    return pack


def grid_nodes(width: int, height: int, step: int) -> tuple[int, int]:
    """(columns, rows) of the nodes of a bearing grid every ``step`` pixels over a width x height sensor: nodes at
    0, step, 2 step, ... up to one past the last pixel's cell (:meth:`IWEWorkspace.pack`)."""
    return (width - 1) // step + 2, (height - 1) // step + 2


def grid_bearings_numpy(grid, x, y, step: int, width: int, dtype=np.float32) -> np.ndarray:
    """Twin of kernel ``pack``'s grid table (test oracle): (n, 3) bearings of pixels (x, y) interpolated bilinearly
    between the nodes of ``grid`` ((nodes, >= 3), rows of ``grid_nodes(width, ...)[0]`` nodes), in ``dtype``."""
    g = np.asarray(grid, dtype)
    x, y = np.asarray(x, np.int64), np.asarray(y, np.int64)
    gw = grid_nodes(width, 1, step)[0]
    gx, gy = x // step, y // step
    ax = ((x - gx * step).astype(dtype) / dtype(step))[:, None]
    ay = ((y - gy * step).astype(dtype) / dtype(step))[:, None]
    r = gy * gw + gx
    one = dtype(1.0)
    out = ((one - ay) * ((one - ax) * g[r, :2] + ax * g[r + 1, :2])
           + ay * ((one - ax) * g[r + gw, :2] + ax * g[r + gw + 1, :2]))
    return np.concatenate([out, g[r, 2:3]], axis=1)


def pack_numpy(t, x, y, lut, start: int, step: int, n: int, t_ref: float, dxy=None, offset: int = 0,
               width: int | None = None, dtype=np.float32, separable: bool = False, grid: int = 0) -> np.ndarray:
    """Twin of kernel ``pack`` (test oracle): (n, 4) rows bx + dx, by + dy, bz, dt of events start + j step."""
    idx = start + step * np.arange(n)
    xs, ys = np.asarray(x)[idx].astype(np.int64), np.asarray(y)[idx].astype(np.int64)
    lut = np.asarray(lut, dtype)
    if separable:
        out = np.stack([lut[xs, 0], lut[ys, 1], lut[ys, 2], lut[ys, 3]], axis=1)
    elif grid:
        out = np.zeros((n, 4), dtype)
        out[:, :3] = grid_bearings_numpy(lut, xs, ys, grid, int(width), dtype)
    else:
        out = lut[ys * int(width) + xs].copy()
    if dxy is not None:
        out[:, :2] += np.asarray(dxy, dtype)[offset:offset + n]
    out[:, 3] = (np.asarray(t, np.float64)[idx] - t_ref).astype(dtype)
    return out


class IWEWorkspace:
    """Compiled kernels and buffers for one sensor size, dtype, blur and packet capacity.

    Usage: ``ws.set_packet(bearings, dts)`` once per packet, then ``ws.evaluate(omega, K)`` per
    optimizer step. A packet larger than the capacity rebuilds the kernels with a doubled capacity
    (a compile, so size the workspace for the largest packet up front).

    Threads: by default (``parts`` None) the event loops run serially on the calling thread, whatever the Taichi
    thread count. A packet's vote and gather are memory-bound scatters and gathers of ~0.2-3 ms: a second thread
    saved at most ~10 % of them, while handing a loop to Taichi's thread pool costs 45-100+ us per launch, more when
    the pool's thread has gone idle between evaluations (the optimiser's Python runs between them), so serial loops
    are the faster choice for front-end packets. ``parts`` = P splits the events into P parts voted in parallel
    (P copies of I; P a multiple of the thread count or below it, ``runtime.check_parts``).
    """

    def __init__(self, width: int, height: int, dtype=np.float32, blur_sigma: float = 1.0,
                 capacity: int = 1 << 14, truncate: float = 4.0, parts: int | None = None):
        self.width, self.height = int(width), int(height)
        self.dtype = np.dtype(dtype)
        if self.dtype not in _DTYPES:
            raise ValueError(f"dtype must be float32 or float64, got {self.dtype}")
        self.taps2 = gram_taps(blur_sigma, truncate).astype(self.dtype)
        self.blur_sigma = float(blur_sigma)
        self.truncate = float(truncate)
        self.capacity = 1 << max(10, int(np.ceil(np.log2(max(int(capacity), 1)))))
        # copies of I voted into without atomics by one parallel part each (default None: serial, one copy)
        self.parts = int(parts) if parts else None
        self._kernels = None
        self._prm = np.zeros(SMALL_SLOT + 1)  # evaluate's parameters and results (kernel arguments)
        self.n = 0
        self.dt_max = 0.0  # max |dt_k| of the packet (whether its angles are small at a given omega)
        self._packed = np.zeros((4, 1), self.dtype)  # the current packet, rows bx, by, bz, dt (read in place)
        self._own = np.zeros((4, 1024), self.dtype)  # the packet buffer ``pack`` fills (grown as needed)
        self._pack_prm = np.zeros(11)
        self._no_dither = np.zeros((1, 2), self.dtype)
        self._packer = None  # BoundLaunch of kernel ``pack`` (built on first use)

    def _ensure(self):
        if self._kernels is None:
            ensure_init()
            parts = check_parts(self.parts) if self.parts else 1
            self._kernels = _build(_DTYPES[self.dtype], self.height, self.width, self.capacity, parts,
                                   self.parts is None or num_threads() == 1)
            self._img = np.zeros((parts * self.height, self.width), self.dtype)  # the parts' copies of I
            self._himg = np.zeros((self.height, self.width), self.dtype)  # H = G2 I (gather's input)
            self._parts = parts
            self._bind()
        return self._kernels

    def _bind(self) -> None:
        """Bind vote and gather to the packet and the buffers (runtime.BoundLaunch: ~2 us per launch instead of
        Taichi's ~60 us of Python; two launches per evaluation); a new packet rebinds the packet only."""
        vote, gather, _ = self._kernels
        self._vote = BoundLaunch(vote, self._packed, self._img, self._prm)
        self._gather = BoundLaunch(gather, self._packed, self._himg, self._prm)

    def compile(self) -> None:
        """Build (or fetch from the offline cache) the kernels an estimation uses, e.g. to time compilation apart
        (not ``iwe``'s display kernel: every command pays the start-up)."""
        self._ensure()
        one = np.zeros(1, np.uint16)
        self.pack(np.zeros(1), one, one, np.array([[0.0, 0.0, 1.0, 0.0]], self.dtype), 1, 0, 1, 1, 0.0)
        self.evaluate(np.zeros(3), np.eye(3))

    def set_packet(self, bearings: np.ndarray, dts: np.ndarray) -> None:
        """Upload one packet: bearings (N, 3) and relative times dt_k = t_k - t_ref (N,)."""
        n = len(dts)
        packed = np.empty((4, max(n, 1)), self.dtype)
        if n:
            packed[:3, :n] = np.asarray(bearings).T
            packed[3, :n] = dts
        self.set_packed(packed, n)

    def rows(self) -> np.ndarray:
        """The current packet as (N, 4) rows bx, by, bz, dt_k (a copy)."""
        return self._packed[:, :self.n].T.copy()

    def pack(self, t: np.ndarray, x: np.ndarray, y: np.ndarray, lut: np.ndarray, width: int, start: int, step: int,
             n: int, t_ref: float, dxy: np.ndarray | None = None, offset: int = 0, separable: bool = False,
             grid: int = 0) -> float:
        """Set the packet from events read in place (``t`` float64, ``x``, ``y`` uint16 pixels, C-contiguous): rows
        j < n from events start + j step (1 of step: a thinned packet without copying it first), bearing
        lut[y * width + x] ((pixels, >= 3) of this dtype) plus dither row offset + j of ``dxy`` ((rows, 2), or None),
        dt = t - t_ref. One launch into a buffer the workspace keeps (a numpy gather, copy and add per packet cost
        ~30 ns per event). Returns max |dt| over the rows. ``separable``: the bearing is (lut[x, 0], lut[y, 1],
        lut[y, 2]), a table of max(width, height) rows: an undistorted camera's bearing is ((x - cx) / fx,
        (y - cy) / fy, 1), the same numbers as its per-pixel table, from a table of a few kB that stays in the L1
        cache where the per-pixel one (5-15 MB on VGA and HD) is read at random from memory. ``grid`` g > 0 (a
        distorted camera): ``lut`` holds the bearings at the nodes of a grid every g pixels (``grid_nodes``), and a
        pixel's bearing is their bilinear interpolation: a table of a few to a few hundred kB in the cache instead
        of random reads of the per-pixel one (HD, 15 MB: 20 -> 11 ns per event in a front-end run)."""
        self._ensure()
        n = int(n)
        if n > self._own.shape[1]:
            self._own = np.zeros((4, max(n, 2 * self._own.shape[1])), self.dtype)
        if n:
            dither = dxy if dxy is not None else self._no_dither
            self._pack_prm[:7] = (start, step, n, t_ref, width, dxy is not None, offset)
            self._pack_prm[8:11] = (bool(separable), grid, grid_nodes(width, 1, grid)[0] if grid else 0)
            args = (t, x, y, lut, dither, self._own, self._pack_prm)
            if self._packer is None:
                self._packer = BoundLaunch(_pack_kernel(_DTYPES[self.dtype]), *args)
            else:
                for i, a in enumerate(args):
                    if a is not self._packer._args[i]:
                        self._packer.set_array(i, a)
            self._packer()
        self.set_packed(self._own, n, float(self._pack_prm[7]) if n else 0.0)
        return self.dt_max

    def set_packed(self, packed: np.ndarray, n: int | None = None, dt_max: float | None = None) -> None:
        """Set the packet: a C-contiguous (4, >= N) array of this workspace's dtype, rows bx, by, bz, dt_k (one
        row per quantity: the kernels' vectorised loops read them as contiguous lanes), and max |dt_k| when known.
        The kernels read it in place (kept by reference: do not modify it while evaluating; copying it into a field
        cost 0.13-0.24 ms per packet, more than the extra ndarray argument of each evaluation)."""
        if packed.dtype != self.dtype or not packed.flags.c_contiguous or packed.ndim != 2 or packed.shape[0] != 4:
            raise ValueError(f"packed must be a C-contiguous (4, N) {self.dtype} array")
        n = packed.shape[1] if n is None else int(n)
        if dt_max is None:
            dt_max = float(np.max(np.abs(packed[3, :n]))) if n else 0.0
        self.dt_max = dt_max
        if n > self.capacity:
            self.capacity = 1 << int(np.ceil(np.log2(n)))
            self._kernels = None
        same = packed is self._packed  # the buffer ``pack`` fills: the launches are bound to it already
        self._packed = packed if packed.shape[1] else np.zeros((4, 1), self.dtype)
        self.n = n
        if self._kernels is None:
            self._ensure()  # built (or rebuilt for the capacity) at the upload, as before the first evaluation
        elif not same:
            self._vote.set_array(0, self._packed)
            self._gather.set_array(0, self._packed)

    def evaluate(self, omega, K, measure: str = "variance", with_grad: bool = True):
        """(contrast, gradient (3,), number of events landing in the image) at omega; raw contrast as in
        the module docstring (normalise in the caller). The gradient is zero when with_grad is False."""
        self._ensure()
        prm = self._prm
        prm[:10] = (self.n, omega[0], omega[1], omega[2], K[0, 0], K[1, 1], K[0, 2], K[1, 2], measure_id(measure),
                    bool(with_grad))
        prm[SMALL_SLOT] = (omega[0] ** 2 + omega[1] ** 2 + omega[2] ** 2) * self.dt_max ** 2 < SERIES_TH2
        img = self._img
        self._vote()  # vote(packed, img, prm)
        total = img if self._parts == 1 else img.reshape(self._parts, self.height, self.width).sum(axis=0)
        # pass 2: H = G2 I (zero padding: exact, see the module docstring)
        himg = separable_blur(total, self.taps2, out=self._himg)
        npix = float(self.width * self.height)
        if not with_grad:  # the cost alone from the images: <I, G2 I> - mu' sum(I), no pass over the events
            mu = prm[10] / npix if measure_id(measure) == 0 else 0.0
            # einsum, not np.dot: a BLAS dot this long wakes OpenBLAS's threads, which then spin beside the kernels
            cost = (float(np.einsum("ij,ij->", total, himg, dtype=np.float64)) - mu * prm[10]) / npix
            img.fill(0)
            return cost, np.zeros(3), int(prm[15])
        img.fill(0)  # the copies of I for the next evaluation
        self._gather()  # gather(packed, himg, prm)
        o = prm[10:16]
        # pass 3 summed w (H - mu') = <I, G2 I> - mu' sum(I), mu' = mu (variance) or 0: that is C * Np
        cost = o[1] / npix
        return cost, (2.0 / npix) * o[2:5], int(o[5])

    def gradient_covariance(self) -> np.ndarray:
        """Noise covariance (3, 3) of the last evaluation's gradient, raw like ``evaluate``'s, from its per-event
        terms (kernel ``gather``'s partial sums per group of _GROUP events, their sums of products in prm[16:22]):
        the number of groups times the groups' covariance, the groups taken as independent draws. At omega = 0 the
        gradient is sum_k dt_k v_k with v_k a function of the event positions alone, so when the events' times do
        not depend on their positions (the events measure no motion) the groups are independent given the positions
        and the estimate is unbiased. Only after an evaluation with the gradient; nan with fewer than 16 groups."""
        groups = (self.n + _GROUP - 1) // _GROUP
        if groups < 16:
            return np.full((3, 3), np.nan)
        xx, xy, xz, yy, yz, zz = self._prm[16:22]
        total = self._prm[12:15]
        scatter = np.array([[xx, xy, xz], [xy, yy, yz], [xz, yz, zz]]) - np.outer(total, total) / groups
        return scatter * (groups / (groups - 1.0)) * (2.0 / (self.width * self.height)) ** 2

    def iwe(self, omega, K, blurred: bool = True) -> np.ndarray:
        """Image of warped events of the current packet at omega, (height, width) float64;
        blurred with G (zero padding) unless ``blurred`` is False."""
        render = self._ensure()[2]
        dst = np.zeros((self.height, self.width), self.dtype)
        render(self._packed, self.n, float(omega[0]), float(omega[1]), float(omega[2]),
               float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]), dst)
        img = dst.astype(np.float64)
        return _blur_np(img, gaussian_taps(self.blur_sigma, self.truncate)) if blurred else img


def contrast_and_gradient(bearings, dts, omega, K, width, height, measure="variance", blur_sigma=1.0,
                          dtype=np.float32, with_grad: bool = True):
    """One-shot convenience wrapper around :class:`IWEWorkspace` (compiles on first use per size/dtype)."""
    ws = IWEWorkspace(width, height, dtype, blur_sigma, capacity=len(dts))
    ws.set_packet(bearings, dts)
    c, g, _ = ws.evaluate(omega, K, measure, with_grad)
    return c, g


# ----------------------------------------------------------------------------------------------
# numpy twin (float64): the same math, used as the test oracle
# ----------------------------------------------------------------------------------------------

def _coeffs_np(th2):
    th = np.sqrt(th2)
    small = th2 < 0.01
    ts = np.where(small, 1.0, th)
    a = np.where(small, 1 - th2 / 6 * (1 - th2 / 20 * (1 - th2 / 42)), np.sin(ts) / ts)
    b = np.where(small, 0.5 - th2 / 24 * (1 - th2 / 30 * (1 - th2 / 56)), 2 * np.sin(0.5 * ts) ** 2 / ts**2)
    c = np.where(small, 1 / 6 - th2 / 120 * (1 - th2 / 42 * (1 - th2 / 72)), (ts - np.sin(ts)) / ts**3)
    return a, b, c


def warp_numpy(bearings, dts, omega):
    """Rotated bearings exp([omega]x dt_k) b_k (N,3), with phi (N,3) and the B, C coefficients."""
    b = np.asarray(bearings, float).reshape(-1, 3)
    phi = np.asarray(omega, float)[None, :] * np.asarray(dts, float).reshape(-1)[:, None]
    a, bb, c = _coeffs_np(np.einsum("ij,ij->i", phi, phi))
    pb = np.cross(phi, b)
    xr = b + a[:, None] * pb + bb[:, None] * np.cross(phi, pb)
    return xr, phi, bb, c


def _blur_np(img, taps):
    from scipy.ndimage import correlate1d

    out = correlate1d(img, taps, axis=1, mode="constant", cval=0.0)
    return correlate1d(out, taps, axis=0, mode="constant", cval=0.0)


def _project_np(xr, K, width, height):
    z = xr[:, 2]
    front = z > 1e-6
    zs = np.where(front, z, 1.0)
    u = K[0, 0] * xr[:, 0] / zs + K[0, 2]
    v = K[1, 1] * xr[:, 1] / zs + K[1, 2]
    valid = front & (u > -1) & (v > -1) & (u < width) & (v < height)
    return u, v, zs, valid


def vote_numpy(bearings, dts, omega, K, width, height) -> np.ndarray:
    """Unblurred IWE I (height, width) float64 (bilinear votes of in-bounds neighbours)."""
    xr, *_ = warp_numpy(bearings, dts, omega)
    u, v, _, valid = _project_np(xr, K, width, height)
    return bilinear.vote_numpy(np.zeros((height, width)), u[valid], v[valid])


def contrast_numpy(bearings, dts, omega, K, width, height, measure="variance", blur_sigma=1.0, truncate=4.0,
                   per_event: bool = False):
    """Float64 twin of the kernel: (contrast, gradient (3,)), or with ``per_event`` the gradient's terms (N, 3)."""
    mid = measure_id(measure)
    xr, phi, bb, c = warp_numpy(bearings, dts, omega)
    dts = np.asarray(dts, float).reshape(-1)
    fx, fy = K[0, 0], K[1, 1]
    u, v, zs, valid = _project_np(xr, K, width, height)
    img = bilinear.vote_numpy(np.zeros((height, width)), u[valid], v[valid])
    npix = width * height
    himg = _blur_np(img, gram_taps(blur_sigma, truncate))  # G2 I
    mu = img.sum() / npix if mid == 0 else 0.0
    cost = np.sum(img * himg) / npix - mu * mu
    _, gu, gv = bilinear.sample_numpy(himg - mu, u, v)  # in-bounds neighbours only; invalid events dropped below
    iz = 1.0 / zs
    a = np.stack([fx * gu * iz, fy * gv * iz, -(fx * gu * xr[:, 0] + fy * gv * xr[:, 1]) * iz * iz], axis=1)
    cc = np.cross(xr, a)
    pc = np.cross(phi, cc)
    gk = dts[:, None] * (cc - bb[:, None] * pc + c[:, None] * np.cross(phi, pc))
    gk[~valid] = 0.0
    terms = 2.0 / npix * gk
    return cost, (terms if per_event else terms.sum(axis=0))


def gradient_covariance_numpy(terms) -> np.ndarray:
    """Twin of ``IWEWorkspace.gradient_covariance`` from the gradient's per-event terms (N, 3)."""
    groups = np.add.reduceat(np.asarray(terms, float), np.arange(0, len(terms), _GROUP))
    return np.cov(groups.T) * len(groups) if len(groups) >= 16 else np.full((3, 3), np.nan)


__all__ = [
    "MEASURES", "IWEWorkspace", "gaussian_taps", "gram_taps", "measure_id", "contrast_and_gradient",
    "warp_numpy", "vote_numpy", "contrast_numpy", "gradient_covariance_numpy", "pack_numpy", "grid_nodes",
    "grid_bearings_numpy",
]
