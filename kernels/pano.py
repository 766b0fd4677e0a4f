"""Panoramic image of warped events (IWE) for the back-end: voting, blur, Var(I_L + alpha I_G) and its gradient.

Objective (paper Eq. 18):  Var( B(I_L) + alpha G ),  variance over all w*h pixels (divided by w*h), where
B is the Gaussian blur (sigma = backend_blur_sigma, radius round(4 sigma) like scipy, wrap along u, zeros beyond
the top/bottom rows), I_L the bilinear votes of the window's events and G = B(I_G) the BLURRED global map:
``PanoIWE`` takes the raw accumulated I_G and blurs it once (B is linear, so B(I_L + alpha I_G) = B(I_L) + alpha G).

Events come in batches of ``batch_size`` consecutive events that share the pose R_b = R(t_b) at the batch's
mid-time (t_first + t_last) / 2, and its Jacobians w.r.t. the degree + 1 control poses (``ti_cmax.spline``,
LEFT perturbations R_k <- exp(delta_k) R_k). A bearing b (unit-depth plane) goes to X' = R_b b and then to
(u, v) per CONVENTIONS.md: lon = atan2(X, Z), lat = atan2(Y, sqrt(X^2 + Z^2)), u = w/2 + w lon / 2pi,
v = h/2 + h lat / pi; it votes into columns floor(u), floor(u) + 1 (mod w) and rows floor(v), floor(v) + 1
(rows outside the map are dropped).

Gradient (Eq. 19-20) without a per-parameter image: with I = B(I_L) + alpha G and mu its mean,
  dVar = (2/Np) sum_px (I - mu) B(dI_L) = (2/Np) sum_px W dI_L,   W = B(I - mu)   (B is self-adjoint),
and sum_px W I_L = sum_events bilinear_interp(W, p_e), so each event contributes grad(interp W)(p_e) dp/dX' dX'
with dX' = -[X']x omega_b (omega_b = sum_k J_bk delta_k). Per batch the 3-vector g_b = sum_e X'_e x dC/dX'_e is
summed serially (no float atomics), chained to the control poses with J_bk^T g_b, and reduced on the host.
The window's votes are accumulated by one serial loop (no atomics), so cost and gradient are bit-reproducible.

Only a bounding box of the touched rows/columns (cyclic in u) plus the blur radius is ever blurred; the
variance of the rest of the map comes from per-window constants of G. f32 is the production path, f64 the
finite-difference path (kernels are built per dtype and degree and cached); the f32 path uses a polynomial
atan2 (<= 2.1e-6 rad error: 0.002 map px at the widest map, 8192 px; about 6x faster than ti.atan2), the f64 path ti.atan2. The numpy twins
(``pano_iwe_numpy``, ``vote_map_numpy``, ``equirect_numpy``) work on the full map with scipy and are the oracles.
"""
import functools
import math
from types import SimpleNamespace

import numpy as np

from ti_cmax.metrics import event_area_percent

from . import bilinear
from .bilinear import ADD, bilinear_funcs
from .blur import TRUNCATE, blur_radius, gaussian_taps, separable_blur
from .runtime import PART_TASK, check_parts, ensure_init, even_slice, num_threads, part_slice, ti
from .spline import spline_funcs



# ----------------------------------------------------------------------------------------------------------------
# host-side helpers and numpy twins
# ----------------------------------------------------------------------------------------------------------------
def blur_map(img: np.ndarray, sigma: float) -> np.ndarray:
    """Panoramic Gaussian blur (wrap along u = columns, zeros beyond the top and bottom rows), float64."""
    from scipy.ndimage import gaussian_filter1d  # here: importing scipy.ndimage costs ~0.15 s of every start-up

    img = np.asarray(img, dtype=np.float64)
    if sigma <= 0:
        return img.copy()
    out = gaussian_filter1d(img, sigma, axis=1, mode="wrap", truncate=TRUNCATE)
    return gaussian_filter1d(out, sigma, axis=0, mode="constant", cval=0.0, truncate=TRUNCATE)


def event_area(img: np.ndarray, lambda0: float = 1.0) -> float:
    """Event area of an IWE, sum_px (1 - exp(-H / lambda0)) (paper Eq. 16, [26]), in pixels."""
    img = np.asarray(img)
    return event_area_percent(img, lambda0) * img.size / 100.0


def event_density(img: np.ndarray, lambda0: float = 1.0) -> float:
    """rho(H) = N_e(H) / area(H) (Eq. 16), N_e = sum of the map; 0 for an empty map."""
    area = event_area(img, lambda0)
    return float(np.sum(img, dtype=np.float64) / area) if area > 0 else 0.0


def batch_mid_times(times: np.ndarray, batch_size: int, index: np.ndarray | None = None) -> np.ndarray:
    """Mid-time (t_first + t_last) / 2 of each batch of ``batch_size`` consecutive events (last batch partial); of
    the events times[index] when ``index`` is given (a sample: only its batches' first and last times are read)."""
    times = np.asarray(times, dtype=np.float64).reshape(-1)
    n = len(times) if index is None else len(index)
    first = np.arange(0, n, batch_size)
    last = np.minimum(first + batch_size - 1, n - 1)
    if index is not None:
        first, last = index[first], index[last]
    return 0.5 * (times[first] + times[last])


def equirect_numpy(xw: np.ndarray, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """Equirectangular (u, v) of world directions (N, 3) per CONVENTIONS.md."""
    x, y, z = xw[:, 0], xw[:, 1], xw[:, 2]
    lon = np.arctan2(x, z)
    lat = np.arctan2(y, np.hypot(x, z))
    return width / 2 + width * lon / (2 * np.pi), height / 2 + height * lat / np.pi


def vote_map_numpy(bearings, rotations, width, height, batch_size=None, out=None) -> np.ndarray:
    """Twin of ``vote_map``: bilinear votes of R b (per-event or per-batch rotations), float64 (h, w)."""
    b = np.asarray(bearings, dtype=np.float64).reshape(-1, 3)
    rot = np.asarray(rotations, dtype=np.float64).reshape(-1, 3, 3)
    if batch_size:
        rot = np.repeat(rot, batch_size, axis=0)[: len(b)]
    xw = np.einsum("nij,nj->ni", rot, b)
    u, v = equirect_numpy(xw, width, height)
    return bilinear.vote_numpy(np.zeros((height, width)) if out is None else out, u, v, wrap_u=True)


def pano_iwe_numpy(
    bearings, batch_s, batch_u, control_R, degree, width, height, sigma=1.0, global_blurred=None, alpha=1.0,
    batch_size=100, with_grad=True,
):
    """Full-map float64 twin of ``PanoIWE.cost_and_grad``: returns (variance, grad (M, 3), I = B(I_L) + alpha G)."""
    from ti_cmax.spline import SO3Spline

    ctrl = np.asarray(control_R, dtype=np.float64).reshape(-1, 3, 3)
    spline = SO3Spline(degree, 0.0, 1.0, ctrl)
    first, r_b, j_b = spline.jacobians_at(batch_s, batch_u)
    b = np.asarray(bearings, dtype=np.float64).reshape(-1, 3)
    bid = np.arange(len(b)) // batch_size
    xw = np.einsum("nij,nj->ni", r_b[bid], b)
    u, v = equirect_numpy(xw, width, height)
    img = blur_map(bilinear.vote_numpy(np.zeros((height, width)), u, v, wrap_u=True), sigma)
    if global_blurred is not None:
        img = img + alpha * np.asarray(global_blurred, dtype=np.float64)
    mu = img.mean()
    var = float(np.mean((img - mu) ** 2))
    if not with_grad:
        return var, None, img
    wmap = blur_map(img - mu, sigma)
    _, gu, gv = bilinear.sample_numpy(wmap, u, v, wrap_u=True)  # d interp(W)/du, d/dv (W = 0 beyond the rows)
    x, y, z = xw[:, 0], xw[:, 1], xw[:, 2]
    rho2 = x * x + z * z
    rho = np.sqrt(rho2)
    r2 = rho2 + y * y
    du = (width / (2 * np.pi)) * np.stack([z / rho2, np.zeros_like(x), -x / rho2], 1)
    dv = (height / np.pi) * np.stack([-x * y, rho2, -z * y], 1) / (rho * r2)[:, None]
    g_x = gu[:, None] * du + gv[:, None] * dv
    g_ev = np.cross(xw, g_x)  # dC/domega for the left perturbation X' <- exp(omega) X'
    g_batch = np.zeros((len(batch_s), 3))
    np.add.at(g_batch, bid, g_ev)
    grad = np.zeros((len(ctrl), 3))
    for k in range(degree + 1):
        np.add.at(grad, first + k, np.einsum("nji,nj->ni", j_b[:, k], g_batch))
    return var, grad * (2.0 / (width * height)), img


# ----------------------------------------------------------------------------------------------------------------
# Taichi kernels
# ----------------------------------------------------------------------------------------------------------------
def _ti_dtype(np_dtype):
    return ti.f64 if np.dtype(np_dtype) == np.float64 else ti.f32


def _proj_funcs(dtype):
    """(project, project_jacobian) ti.funcs for one float dtype (mapping, trackers); all four: _proj_all."""
    f = _proj_all(dtype)
    return f.project, f.project_jacobian


@functools.cache
def _proj_all(dtype) -> SimpleNamespace:
    """ti.funcs project, project_basis, project_jacobian and cross_gradient for one float dtype."""
    vec3 = ti.types.vector(3, dtype)

    @ti.func
    def fmin(a, b):
        """min(a, b) for non-NaN a, b: one minss (ti.min adds NaN handling: a compare, a blend and a branch)."""
        return ti.select(a < b, a, b)

    @ti.func
    def fmax(a, b):
        return ti.select(a > b, a, b)

    @ti.func
    def fast_atan2(y, x):
        """Branch-free f32 atan2, |error| <= 2.1e-6 rad (measured on 2 M random directions; 0.0006 map px on a
        2048-wide map, 0.002 on the widest, 8192: far below the blur's 1 px, and a fixed smooth distortion of the
        map that every evaluation shares).

        Taichi's ti.atan2 costs ~36 ns per call on this CPU, this ~6 ns: the projection dominates the per-event
        cost. atan(a) on a = min/max in [0, 1] by an odd degree-11 polynomial (least squares on Chebyshev nodes), then
        octant fixes. The degree-15 one before (3.5e-7 rad) cost 4-8 % more per back-end evaluation. Min/max by
        selects (fmin/fmax): ti.min/ti.max compile to NaN-safe sequences with a branch, ~10 more instructions.
        """
        ay = ti.abs(y)
        ax = ti.abs(x)
        a = fmin(ax, ay) / fmax(fmax(ax, ay), ti.f32(1e-30))
        z = a * a
        r = a * (ti.f32(0.99997983) + z * (ti.f32(-0.33265548) + z * (ti.f32(0.19367032) + z * (
            ti.f32(-0.11665112) + z * (ti.f32(0.05282349) + z * ti.f32(-0.0117705))))))
        r = ti.select(ay > ax, ti.f32(1.5707963268) - r, r)
        r = ti.select(x < 0, ti.f32(3.1415926536) - r, r)
        return ti.select(y < 0, -r, r)

    @ti.func
    def atan2(y, x):
        res = ti.cast(0.0, dtype)
        if ti.static(dtype == ti.f32):
            res = fast_atan2(y, x)
        else:
            res = ti.atan2(y, x)
        return res

    @ti.func
    def project_basis(x, width, height, su, sv):
        """(u, v) of X' and (s, c, t) = (X, Z, Y) / sqrt(X^2 + Z^2) = (sin lon, cos lon, tan lat), which is all that
        X' x dC/dX' needs (``cross_gradient``); su = w / 2pi and sv = h / pi come in as kernel arguments (exact in
        f64, unlike a Python float literal, which Taichi rounds to f32 first)."""
        rho = ti.sqrt(x[0] * x[0] + x[2] * x[2])
        lon = atan2(x[0], x[2])
        lat = atan2(x[1], rho)
        pu = ti.cast(0.5, dtype) * ti.cast(width, dtype) + su * lon
        pv = ti.cast(0.5, dtype) * ti.cast(height, dtype) + sv * lat
        inv_rho = ti.cast(1.0, dtype) / rho
        return pu, pv, vec3(x[0] * inv_rho, x[2] * inv_rho, x[1] * inv_rho)

    @ti.func
    def project(x, width, height, su, sv):
        """(u, v) of X' (``project_basis`` without the basis: the compiler drops its unused arithmetic)."""
        pu, pv, _ = project_basis(x, width, height, su, sv)
        return pu, pv

    @ti.func
    def cross_gradient(q, gu, gv, su, sv):
        """X' x dC/dX' for the map gradient (gu, gv) = (dC/du, dC/dv) at X', from q = (s, c, t) of project_basis.

        With du/dX' = su (Z, 0, -X) / rho^2 and dv/dX' = sv (-X Y, rho^2, -Z Y) / (rho r^2) (``project_jacobian``):
        X' x du/dX' = su (-s t, 1, -c t) and X' x dv/dX' = sv (-c, 0, s) (r^2 = X^2 + Y^2 + Z^2, rho^2 = X^2 + Z^2):
        no square root, division or cross product per event."""
        a = gu * su
        b = gv * sv
        return vec3(-(a * q[0] * q[2] + b * q[1]), a, b * q[0] - a * q[1] * q[2])

    @ti.func
    def project_jacobian(x, su, sv):
        """Rows d u / d X' and d v / d X' (paper Eq. 27-29 with the pixel scaling)."""
        rho2 = x[0] * x[0] + x[2] * x[2]
        r2 = rho2 + x[1] * x[1]
        inv_rho = ti.rsqrt(rho2)
        a = su * inv_rho * inv_rho
        c = sv * inv_rho / r2
        du = vec3(x[2] * a, 0, -x[0] * a)
        dv = vec3(-x[0] * x[1] * c, rho2 * c, -x[2] * x[1] * c)
        return du, dv

    return SimpleNamespace(project=project, project_basis=project_basis, project_jacobian=project_jacobian,
                           cross_gradient=cross_gradient, fmin=fmin, fmax=fmax)


# events per batch projected at once into local arrays before they are voted (see _iwe_kernels)
CHUNK = 32


@functools.cache
def _iwe_kernels(dtype, degree: int, serial: bool = False):
    """Kernels of one cost/gradient evaluation for one dtype and spline degree (the blurs run in OpenCV between
    them: kernels/blur.py). ``serial`` (one thread): every loop runs on the calling thread; a parallel loop
    costs 65-100 us per launch even with one thread (measured, 2 loops of 100 iterations: 145-217 us against
    24-33 us serialized). With several threads each loop runs over ``tasks`` = P x PART_TASK iterations (P the vote
    parts, the thread count) that spread the batches or rows evenly: Taichi makes a loop of N iterations tasks of
    max(512, N / threads) (kernels/runtime.py), so a loop over the 2 parts or the few hundred buffer rows ran on one
    thread.

    Every per-event loop that does not vote stores nothing to memory (the bounding boxes and the gradient are
    reductions in registers): Taichi reloads an ndarray's address from the argument buffer after every store, which
    keeps LLVM from vectorizing a loop that stores, so these loops recompute the projection from the bearings (one
    array per coordinate) instead of storing and reloading (u, v) per event, and run 8 events per instruction (the
    projection costs ~2.5 instead of ~13 ns per event). The vote projects ``CHUNK`` events into local arrays (not
    ndarrays: no reload) and then votes them one by one."""
    spl = spline_funcs(dtype, degree)
    bl = bilinear_funcs(dtype)
    pf = _proj_all(dtype)
    mat3 = ti.types.matrix(3, 3, dtype)
    vec3 = ti.types.vector(3, dtype)
    order = degree + 1

    @ti.func
    def bearing(bt: ti.template(), e):
        return vec3(bt[0, e], bt[1, e], bt[2, e])

    @ti.func
    def buffer_corner(u, v, c0, r0, width, bw, bh):
        """Window-buffer corner of the point (u, v) and its fractions, branch-free (vectorizable): (buffer columns
        ia, ib of map columns floor(u), floor(u) + 1 modulo the width, buffer row ja of floor(v), whether ia, ib,
        ja, ja + 1 lie in the buffer, fu, fv). u in [-w, 2w) as the projection gives it; outside it (a non-finite
        point) every corner is out of the buffer."""
        i0, j0, fu, fv = bl.split(u, v)
        ia = i0 - c0
        ia = ti.select(ia < 0, ia + width, ia)
        ia = ti.select(ia >= width, ia - width, ia)
        ib = ia + 1
        ib = ti.select(ib >= width, ib - width, ib)
        ja = j0 - r0
        return (ia, ib, ja, bl.in_range(ia, bw), bl.in_range(ib, bw), bl.in_range(ja, bh), bl.in_range(ja + 1, bh),
                fu, fv)

    @ti.kernel
    def k_poses(
        ctrl: ti.types.ndarray(dtype=mat3, ndim=1),
        batch_s: ti.types.ndarray(dtype=ti.i32, ndim=1),
        batch_u: ti.types.ndarray(dtype=dtype, ndim=1),
        bt: ti.types.ndarray(dtype=dtype, ndim=2),
        batch_size: ti.i32,
        width: ti.i32,
        height: ti.i32,
        su: dtype,
        sv: dtype,
        seg_lo: ti.i32,
        seg_hi: ti.i32,
        om: ti.types.ndarray(dtype=vec3, ndim=1),
        nm: ti.types.ndarray(dtype=mat3, ndim=1),
        rot_out: ti.types.ndarray(dtype=mat3, ndim=1),
        jac_out: ti.types.ndarray(dtype=mat3, ndim=2),
        bbox: ti.types.ndarray(dtype=ti.i32, ndim=2),
        tasks: ti.i32,
        with_grad: ti.i32,
    ):
        """Per batch: its pose (and, ``with_grad`` != 0, the spline's Jacobians) and the bounding box of the pixels its
        rotated bearings (``bt``: (3, n)) touch. First the knot intervals [seg_lo, seg_hi) the batches reach, once
        (spline ``segment``: om, nm).

        Columns are tracked relative to the batch's first event, wrapped to (-w/2, w/2], so the box is a cyclic
        interval [bbox0, bbox1) (unwrapped integers, bbox1 - bbox0 <= w); rows [bbox2, bbox3] clamped to the map.
        """
        n_ev = bt.shape[1]
        half = ti.cast(width // 2, dtype)
        fw = ti.cast(width, dtype)
        nb = batch_s.shape[0]
        ti.loop_config(serialize=True)  # a few intervals: not worth a parallel launch
        for k in range(seg_lo, seg_hi):
            om[k], nm[k] = spl.segment(ctrl, k)
        if ti.static(serial):
            ti.loop_config(serialize=True)
        for it in range(tasks):
            lo, hi = even_slice(it, nb, tasks)
            for b in range(lo, hi):
                r = ti.Matrix.zero(dtype, 3, 3)
                if with_grad:  # a branch per batch, not a template: one compiled kernel for the BA and the settle
                    r = spl.pose_jacobians(ctrl, om, nm, batch_s[b], batch_u[b], jac_out, b)
                else:
                    r = spl.pose_from_segments(ctrl, om, batch_s[b], batch_u[b])
                rot_out[b] = r
                e0 = b * batch_size
                pu0, _ = pf.project(r @ bearing(bt, ti.min(e0, n_ev - 1)), width, height, su, sv)
                ref = ti.floor(pu0)  # columns relative to the batch's first event
                # integer reductions of the floors (floor is monotonic: the floor of the extreme): LLVM vectorizes
                # integer min/max, not float ones without a no-NaN guarantee
                dmin = 0
                dmax = 0
                vmin = height
                vmax = -1
                for e in range(e0, ti.min(e0 + batch_size, n_ev)):  # reductions only: vectorized
                    pu, pv = pf.project(r @ bearing(bt, e), width, height, su, sv)
                    d = pu - ref
                    d = ti.select(d > half, d - fw, d)
                    d = ti.select(d <= -half, d + fw, d)
                    fd = ti.cast(ti.floor(d), ti.i32)
                    fv = ti.cast(ti.floor(pv), ti.i32)
                    dmin = ti.min(dmin, fd)
                    dmax = ti.max(dmax, fd)
                    vmin = ti.min(vmin, fv)
                    vmax = ti.max(vmax, fv)
                iref = ti.cast(ref, ti.i32)
                bbox[b, 0] = iref + dmin
                bbox[b, 1] = iref + dmax + 2  # the right neighbour column is touched too
                bbox[b, 2] = ti.max(vmin, 0)
                bbox[b, 3] = ti.min(vmax + 1, height - 1)

    @ti.kernel
    def k_vote(
        rot: ti.types.ndarray(dtype=mat3, ndim=1),
        bt: ti.types.ndarray(dtype=dtype, ndim=2),
        batch_size: ti.i32,
        width: ti.i32,
        height: ti.i32,
        su: dtype,
        sv: dtype,
        c0: ti.i32,
        r0: ti.i32,
        lambda0: dtype,
        votes: ti.types.ndarray(dtype=dtype, ndim=2),
        buf: ti.types.ndarray(dtype=dtype, ndim=2),
        stats: ti.types.ndarray(dtype=ti.f64, ndim=2),
    ):
        """Vote I_L into the window buffer ``buf`` (unblurred), with per-row sums of the raw votes and of their event
        area 1 - exp(-I / lambda0) (float64; they give the density of I_L for alpha; the area only when lambda0 >= 0,
        i.e. when the caller needs it (-1 otherwise): an exp per buffer pixel).

        ``votes`` holds P = rows / bh copies of the buffer: part p votes the events of batches [p nb/P, (p+1) nb/P)
        into copy p with plain load/add/store, then the copies are summed in a fixed order (no float atomics, which
        were measured 2x slower than serial voting here, and bit-reproducible for a given P; the vote's tasks hold
        whole parts). With P = 1 the caller passes the same array as ``votes`` and ``buf``: the votes are the buffer.
        """
        bh, bw = buf.shape[0], buf.shape[1]
        parts = votes.shape[0] // bh  # votes arrives zeroed (np.zeros: a struct-for clear cost 10 ns per pixel)
        n_ev = bt.shape[1]
        nb = rot.shape[0]
        one = ti.cast(1.0, dtype)
        zero = ti.cast(0.0, dtype)
        if ti.static(serial):
            ti.loop_config(serialize=True)
        for it in range(parts * PART_TASK):
            part, b0, b1 = part_slice(it, nb, parts)
            for b in range(b0, b1):
                r = rot[b]
                c = b * batch_size
                end = ti.min(c + batch_size, n_ev)
                while c < end:
                    m = ti.min(CHUNK, end - c)
                    # per event (vectorized: stores to local arrays only): the buffer rows and columns of its four
                    # corners, clamped into the buffer, and their weights, 0 for a corner outside it
                    ra = ti.Vector([0] * CHUNK, dt=ti.i32)
                    rb = ti.Vector([0] * CHUNK, dt=ti.i32)
                    ca = ti.Vector([0] * CHUNK, dt=ti.i32)
                    cb = ti.Vector([0] * CHUNK, dt=ti.i32)
                    w00 = ti.Vector([0.0] * CHUNK, dt=dtype)
                    w01 = ti.Vector([0.0] * CHUNK, dt=dtype)
                    w10 = ti.Vector([0.0] * CHUNK, dt=dtype)
                    w11 = ti.Vector([0.0] * CHUNK, dt=dtype)
                    for i in range(m):
                        pu, pv = pf.project(r @ bearing(bt, c + i), width, height, su, sv)
                        ia, ib, ja, oka, okb, okr, oks, fu, fv = buffer_corner(pu, pv, c0, r0, width, bw, bh)
                        ra[i] = part * bh + ti.select(okr, ja, 0)
                        rb[i] = part * bh + ti.select(oks, ja + 1, 0)
                        ca[i] = ti.select(oka, ia, 0)
                        cb[i] = ti.select(okb, ib, 0)
                        top = ti.select(okr, one - fv, zero)
                        bottom = ti.select(oks, fv, zero)
                        left = ti.select(oka, one - fu, zero)
                        right = ti.select(okb, fu, zero)
                        w00[i] = top * left
                        w01[i] = top * right
                        w10[i] = bottom * left
                        w11[i] = bottom * right
                    # plain load/add/store (``+=`` would be an atomic add in a parallel loop); a dropped corner adds 0
                    # inside the buffer
                    for i in range(m):
                        votes[ra[i], ca[i]] = votes[ra[i], ca[i]] + w00[i]
                        votes[ra[i], cb[i]] = votes[ra[i], cb[i]] + w01[i]
                        votes[rb[i], ca[i]] = votes[rb[i], ca[i]] + w10[i]
                        votes[rb[i], cb[i]] = votes[rb[i], cb[i]] + w11[i]
                    c += CHUNK
        # per row: the branches outside the pixel loops (inside, with the loop over the parts, they cost ~40
        # instructions per buffer pixel, about as much as the voting per event: ~0.9 buffer pixels per event)
        if ti.static(serial):
            ti.loop_config(serialize=True)
        tasks = parts * PART_TASK
        for it in range(tasks):
            lo, hi = even_slice(it, bh, tasks)
            for i in range(lo, hi):
                raw = ti.cast(0.0, ti.f64)
                area = ti.cast(0.0, ti.f64)
                if parts == 1:  # buf IS votes (the caller passes the same array): nothing to copy
                    for j in range(bw):
                        raw += ti.cast(votes[i, j], ti.f64)
                else:
                    for j in range(bw):
                        acc = votes[i, j]
                        for part in range(1, parts):
                            acc += votes[part * bh + i, j]
                        buf[i, j] = acc
                        raw += ti.cast(acc, ti.f64)
                if lambda0 >= 0:
                    for j in range(bw):
                        area += ti.cast(one - ti.exp(-buf[i, j] / lambda0), ti.f64)
                stats[i, 0] = raw
                stats[i, 1] = area

    @ti.kernel
    def k_stats(
        lmap: ti.types.ndarray(dtype=dtype, ndim=2),
        gmap: ti.types.ndarray(dtype=dtype, ndim=2),
        alpha: dtype,
        r0: ti.i32,
        c0: ti.i32,
        stats: ti.types.ndarray(dtype=ti.f64, ndim=2),
        tasks: ti.i32,
    ):
        """Per-row float64 sums of L = B(I_L), L^2 and L G over the window (reductions only: vectorized)."""
        bh, bw = lmap.shape[0], lmap.shape[1]
        gw = gmap.shape[1]
        if ti.static(serial):
            ti.loop_config(serialize=True)
        for it in range(tasks):
            lo, hi = even_slice(it, bh, tasks)
            for i in range(lo, hi):
                gi = ti.min(r0 + i, gmap.shape[0] - 1)
                s1 = ti.cast(0.0, ti.f64)
                s2 = ti.cast(0.0, ti.f64)
                s3 = ti.cast(0.0, ti.f64)
                if alpha != 0:  # map columns c0 + j, then (past the seam) c0 + j - gw: no branch per pixel
                    n1 = ti.min(bw, gw - c0)
                    for seam in ti.static(range(2)):  # buffer columns [0, n1), then [n1, bw) shifted by -gw
                        for j in range(n1 * seam, n1 + (bw - n1) * seam):
                            val = ti.cast(lmap[i, j], ti.f64)
                            s1 += val
                            s2 += val * val
                            s3 += val * ti.cast(gmap[gi, c0 + j - gw * seam], ti.f64)
                else:
                    for j in range(bw):
                        val = ti.cast(lmap[i, j], ti.f64)
                        s1 += val
                        s2 += val * val
                stats[i, 0] = s1
                stats[i, 1] = s2
                stats[i, 2] = s3

    @ti.kernel
    def k_gradient(
        wmap: ti.types.ndarray(dtype=dtype, ndim=2),
        r0: ti.i32,
        c0: ti.i32,
        rot: ti.types.ndarray(dtype=mat3, ndim=1),
        bt: ti.types.ndarray(dtype=dtype, ndim=2),
        jac: ti.types.ndarray(dtype=mat3, ndim=2),
        batch_size: ti.i32,
        width: ti.i32,
        height: ti.i32,
        su: dtype,
        sv: dtype,
        out: ti.types.ndarray(dtype=vec3, ndim=2),
        tasks: ti.i32,
    ):
        """Per batch g_b = sum_e X'_e x dC/dX'_e from W = B(L + alpha G - mu) on the window, and
        out[b, k] = J_bk^T g_b. The events are projected again (a reduction without stores: vectorized, cheaper than
        storing their (u, v) and basis in the vote and loading them here); W is read at clamped indices and masked,
        so the loop has no branch."""
        bh, bw = wmap.shape[0], wmap.shape[1]
        n_ev = bt.shape[1]
        zero = ti.cast(0.0, dtype)
        if ti.static(serial):
            ti.loop_config(serialize=True)
        nb = jac.shape[0]
        for it in range(tasks):
            lo, hi = even_slice(it, nb, tasks)
            for b in range(lo, hi):
                r = rot[b]
                g = vec3(0, 0, 0)
                for e in range(b * batch_size, ti.min((b + 1) * batch_size, n_ev)):
                    pu, pv, q = pf.project_basis(r @ bearing(bt, e), width, height, su, sv)
                    ia, ib, ja, oka, okb, okr, oks, fu, fv = buffer_corner(pu, pv, c0, r0, width, bw, bh)
                    ca = ti.select(oka, ia, 0)
                    cb = ti.select(okb, ib, 0)
                    ra = ti.select(okr, ja, 0)
                    rb = ti.select(oks, ja + 1, 0)
                    a = ti.Vector([ti.select(okr and oka, wmap[ra, ca], zero), ti.select(okr and okb, wmap[ra, cb], zero),
                                   ti.select(oks and oka, wmap[rb, ca], zero), ti.select(oks and okb, wmap[rb, cb], zero)])
                    _, gu, gv = bl.interp(a, fu, fv)
                    g += pf.cross_gradient(q, gu, gv, su, sv)
                for k in ti.static(range(order)):
                    out[b, k] = jac[b, k].transpose() @ g

    return dict(poses=k_poses, vote=k_vote, stats=k_stats, gradient=k_gradient)


@functools.cache
def _vote_kernel(dtype):
    project, _ = _proj_funcs(dtype)
    bl = bilinear_funcs(dtype)
    mat3 = ti.types.matrix(3, 3, dtype)
    vec3 = ti.types.vector(3, dtype)

    @ti.kernel
    def k(
        bearings: ti.types.ndarray(dtype=vec3, ndim=1),
        rot: ti.types.ndarray(dtype=mat3, ndim=1),
        batch_size: ti.i32,
        su: dtype,
        sv: dtype,
        out: ti.types.ndarray(dtype=dtype, ndim=2),
        track: ti.i32,
        occ_col: ti.types.ndarray(dtype=ti.i32, ndim=1),
        occ_row: ti.types.ndarray(dtype=ti.i32, ndim=1),
        uv: ti.types.ndarray(dtype=dtype, ndim=2),
    ):
        height, width = out.shape[0], out.shape[1]
        for e in range(bearings.shape[0]):  # parallel: rotate and project (the costly part)
            x = rot[e // batch_size] @ bearings[e]
            pu, pv = project(x, width, height, su, sv)
            uv[e, 0] = pu
            uv[e, 1] = pv
        # serial plain adds: bit-reproducible (parallel float atomics sum in a varying order), and no slower here
        ti.loop_config(serialize=True)
        for e in range(bearings.shape[0]):
            i0, j0, fu, fv = bl.split(uv[e, 0], uv[e, 1])
            ia, ib = bl.wrap_cols(i0, width)  # pu in [0, w] up to round-off
            bl.scatter(out, 0, height, j0, ia, ib, 1, 1, fu, fv, ti.cast(1.0, dtype), ADD)
            if track:  # mark the touched columns and rows
                occ_col[ia] = 1
                occ_col[ib] = 1
                occ_row[ti.min(ti.max(j0, 0), height - 1)] = 1
                occ_row[ti.min(ti.max(j0 + 1, 0), height - 1)] = 1

    return k


def vote_map(bearings, rotations, width: int, height: int, batch_size: int | None = None, out=None,
             dtype=np.float32, occupancy: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
    """Accumulate bilinear votes of R b into a panorama (h, w) (polarity ignored).

    ``rotations`` is per event (N, 3, 3) or, with ``batch_size``, per batch of that many consecutive events.
    ``out`` (C-contiguous, of ``dtype``) is accumulated into when given (used to grow the global map I_G).
    ``occupancy`` = (cols (w,) int32, rows (h,) int32) arrays get 1 where a vote landed (see touched_region).
    """
    ensure_init()
    dtype = np.dtype(dtype)
    b = np.ascontiguousarray(bearings, dtype=dtype).reshape(-1, 3)
    rot = np.ascontiguousarray(rotations, dtype=dtype).reshape(-1, 3, 3)
    bs = int(batch_size) if batch_size else 1
    if len(rot) * bs < len(b):
        raise ValueError(f"{len(rot)} rotations (batch size {bs}) for {len(b)} events")
    if out is None:
        out = np.zeros((height, width), dtype=dtype)
    elif out.dtype != dtype or not out.flags.c_contiguous or out.shape != (height, width):
        raise ValueError(f"out must be a C-contiguous {dtype} array of shape {(height, width)}")
    if occupancy is None:
        track, occ_col, occ_row = 0, np.zeros(1, np.int32), np.zeros(1, np.int32)
    else:
        track, (occ_col, occ_row) = 1, occupancy
        if occ_col.shape != (width,) or occ_row.shape != (height,) or occ_col.dtype != np.int32:
            raise ValueError("occupancy must be int32 arrays of shapes (width,) and (height,)")
    if len(b):
        _vote_kernel(_ti_dtype(dtype))(b, rot, bs, width / (2 * math.pi), height / math.pi, out, track,
                                       occ_col, occ_row, np.empty((len(b), 2), dtype))
    return out


def touched_region(occ_col: np.ndarray, occ_row: np.ndarray, margin: int):
    """Smallest cyclic column interval and row range holding every marked column/row, grown by ``margin``.

    Returns (rows slice, column indices (modulo the width)) or None when nothing is marked. The column interval
    is the complement of the largest cyclic gap, so a region straddling the longitude seam stays small.
    """
    cols = np.flatnonzero(occ_col)
    rows = np.flatnonzero(occ_row)
    if len(cols) == 0 or len(rows) == 0:
        return None
    w, h = len(occ_col), len(occ_row)
    gaps = np.diff(np.append(cols, cols[0] + w)) - 1
    k = int(np.argmax(gaps))
    span = w - int(gaps[k])
    first = int(cols[(k + 1) % len(cols)])
    if span + 2 * margin >= w:
        col_idx = np.arange(w)
    else:
        col_idx = (first - margin + np.arange(span + 2 * margin)) % w
    return slice(max(int(rows[0]) - margin, 0), min(int(rows[-1]) + margin + 1, h)), col_idx


def column_selector(cols: np.ndarray):
    """``cols`` (column indices, as touched_region returns them) as a slice when they are one increasing run without
    the seam: indexing with it gives views (no gathers, no scattered writes); else the index array itself."""
    cols = np.asarray(cols)
    if len(cols) and int(cols[-1]) - int(cols[0]) == len(cols) - 1:
        return slice(int(cols[0]), int(cols[-1]) + 1)
    return cols


def _revote_axis(a: np.ndarray, start: int, d: int, axis: int, cyclic: bool = False) -> tuple[int, np.ndarray]:
    """``revote`` along one axis of a 2-D array: fine indices start + i (i < a.shape[axis]) onto coarse I with
    weights (d - |start + i - d I|) / d. Returns (first coarse index, values); ``cyclic``: a whole cyclic axis (start
    0, its length a multiple of d), one value per coarse index."""
    n = a.shape[axis]

    def along(x, sl):  # x[sl] along ``axis``
        return x[sl] if axis == 0 else x[:, sl]

    if cyclic:
        lo, count = 0, n // d
        padded = np.concatenate([along(a, slice(n - (d - 1), n)), a, along(a, slice(0, d - 1))], axis=axis) \
            if d > 1 else a
    else:
        lo = -((d - 1 - start) // d)  # ceil((start - d + 1) / d): the first coarse index a fine one reaches
        count = (start + n - 1 + d - 1) // d - lo + 1
        shape = list(a.shape)
        shape[axis] = count * d + 2 * (d - 1)
        padded = np.zeros(shape, a.dtype)
        first = start - (lo * d - (d - 1))  # where fine index ``start`` goes in ``padded``
        along(padded, slice(first, first + n))[...] = a
    out = along(padded, slice(d - 1, d - 1 + count * d, d)).copy()  # k = 0: weight 1
    pair = np.empty_like(out)  # (one scratch array for every k: a settled stride's region is megabytes)
    for k in range(1, d):
        np.add(along(padded, slice(d - 1 - k, d - 1 - k + count * d, d)),
               along(padded, slice(d - 1 + k, d - 1 + k + count * d, d)), out=pair)
        pair *= a.dtype.type((d - k) / d)
        out += pair
    return lo, out


def revote(votes: np.ndarray, r0: int, cols: np.ndarray, d: int, width: int, height: int):
    """Votes of a map (``width`` x ``height``) on rows r0.. and columns ``cols`` (a cyclic run, or all of them) re-voted
    onto the map d times coarser: each pixel's mass bilinearly at its centre's coarse position (u / d, v / d).

    The coarse map is thereby centred like one voted directly at (u / d, v / d) and spreads a vote by the same rms
    (d^2 / 6 fine px^2 per axis: the fine bilinear vote's 1/6 plus the re-vote's (d^2 - 1) / 6): the loop closer's
    rebuild and the settled strides give the BA's coarse map without a second projection. Returns (rows slice,
    column indices, votes) on the coarse map (rows beyond it dropped, columns modulo width / d)."""
    votes = np.asarray(votes)
    if d == 1:
        return slice(int(r0), int(r0) + len(votes)), np.asarray(cols), votes
    wc, hc = width // d, height // d
    cyclic = len(cols) == width
    r_lo, out = _revote_axis(votes, int(r0), d, 0)  # rows first: the column pass then reads d times less
    c_lo, out = _revote_axis(out, 0 if cyclic else int(cols[0]), d, 1, cyclic)
    top, bottom = max(r_lo, 0), min(r_lo + out.shape[0], hc)
    out = out[top - r_lo:bottom - r_lo]
    if not cyclic and out.shape[1] > wc:  # a run longer than the coarse width: fold it
        folded = np.zeros((out.shape[0], wc), out.dtype)
        np.add.at(folded.T, (c_lo + np.arange(out.shape[1])) % wc, out.T)
        return slice(top, bottom), np.arange(wc), folded
    return slice(top, bottom), (c_lo + np.arange(out.shape[1])) % wc, out


def blur_region(raw: np.ndarray, blurred: np.ndarray, rows: slice, cols: np.ndarray, sigma: float) -> np.ndarray:
    """Recompute ``blurred`` = blur_map(raw) on rows x cols only (in place); returns the old values there.

    The input is read with a margin of the blur radius (wrapping in longitude, zeros beyond the top and bottom),
    so the result equals the full-map blur on the region.
    """
    h, w = raw.shape
    r = blur_radius(sigma)
    sel = (rows, column_selector(cols))
    old = blurred[sel].copy()
    if sigma <= 0:
        blurred[sel] = raw[sel]
        return old
    full_width = len(cols) == w
    r0, r1 = rows.start - r, rows.stop + r
    lo, hi = max(r0, 0), min(r1, h)
    if full_width:
        in_cols = slice(0, w)
    else:
        in_cols = column_selector((cols[0] - r + np.arange(len(cols) + 2 * r)) % w)
    n_in = w if full_width else len(cols) + 2 * r
    src = np.zeros((r1 - r0, n_in), blurred.dtype)
    src[lo - r0 : hi - r0] = raw[lo:hi, in_cols]
    # in the maps' dtype (float32: OpenCV's SIMD pass 2.5x faster than in float64; = scipy's gaussian_filter1d to
    # float32 rounding)
    out = separable_blur(src, gaussian_taps(sigma), wrap_cols=full_width)
    out = out[r : r + (rows.stop - rows.start)]
    if not full_width:
        out = out[:, r : r + len(cols)]
    blurred[sel] = out
    return old


def render_map(bearings, times, pose_fn, width: int, height: int, batch_size: int = 100, out=None,
               dtype=np.float32) -> np.ndarray:
    """Panoramic IWE of events along any trajectory: ``pose_fn(times) -> (N, 3, 3)`` (e.g. ``Trajectory.at`` or
    ``SO3Spline.evaluate``) is queried at the batches' mid-times, as the back-end does."""
    times = np.asarray(times, dtype=np.float64).reshape(-1)
    if len(times) == 0:
        return np.zeros((height, width), dtype=dtype) if out is None else out
    rot = pose_fn(batch_mid_times(times, batch_size))
    return vote_map(bearings, rot, width, height, batch_size=batch_size, out=out, dtype=dtype)


class VoteWork:
    """Work arrays kept from one ``PanoIWE`` to the next (the back-end's settled strides, its BA windows): a new array
    of a stride's size costs a page fault per 4 kB written (about as much as the vote itself), a reused one none.
    Each name holds one flat array that only grows; ``take`` gives a C-contiguous view of its first rows, valid until
    the next ``take`` of that name (the caller is done with a stride's votes, a window's BA, before the next)."""

    def __init__(self):
        self._arrays: dict[str, np.ndarray] = {}

    def take(self, name: str, shape: tuple, dtype, zero: bool = False) -> np.ndarray:
        size = math.prod(shape)
        flat = self._arrays.get(name)
        if flat is None or flat.dtype != np.dtype(dtype) or len(flat) < size:
            # room to grow: strides vary with the event rate (twice the size: a handful of new arrays per run)
            flat = self._arrays[name] = np.empty(max(2 * size, 1024), dtype)
        out = flat[:size].reshape(shape)
        if zero:
            out.fill(0)
        return out


class PanoIWE:
    """Var(B(I_L) + alpha B(I_G)) of one window's events and its gradient w.r.t. the spline's control poses.

    Built once per window (the events, their batches' spline supports and the global map are fixed), then
    ``cost_and_grad(control_R)`` is called by the optimizer. ``batch_s``/``batch_u`` are the spline supports of the
    batches' mid-times (``SO3Spline.support(batch_mid_times(t, batch_size))``); ``global_map`` is the RAW I_G
    (blurred here once) or None. The gradient is (M, 3) float64 w.r.t. left perturbations of all M control poses
    passed (poses the window keeps fixed are the caller's to ignore). Instead of ``global_map``, a caller that keeps
    B(I_G) up to date passes ``global_blurred`` (h, w) with ``global_sums`` = (sum, sum of squares) of it: no
    per-window work over the whole map then (large maps). ``alpha`` may be changed after construction.
    ``alpha_from_density=(rho_g, lambda0)``: alpha = rho(I_L) / rho_g (Eq. 16-17) with I_L the local map of the
    FIRST evaluation (the optimiser's start, the initialization): no separate projection of the events for it.
    ``bearings`` are (n, 3), or (3, n) with ``coordinate_rows`` (one row per coordinate, as the kernels read them and
    the back-end's buffer keeps them: copied row by row instead of transposed).
    """

    def __init__(self, bearings, batch_s, batch_u, degree: int, width: int, height: int, sigma: float = 1.0,
                 global_map=None, alpha: float = 1.0, batch_size: int = 100, dtype=np.float32,
                 global_blurred=None, global_sums: tuple[float, float] | None = None, parts: int | None = None,
                 alpha_from_density: tuple[float, float] | None = None, work: VoteWork | None = None,
                 coordinate_rows: bool = False):
        ensure_init()
        self.dtype = np.dtype(dtype)
        self.degree, self.width, self.height = int(degree), int(width), int(height)
        self.batch_size = int(batch_size)
        # one row per coordinate (3, n): the kernels' per-event loops load 8 consecutive events at once
        src = np.asarray(bearings)
        src = src.reshape(3, -1) if coordinate_rows else src.reshape(-1, 3).T
        if work is None:
            self.bearings_t = np.ascontiguousarray(src, dtype=self.dtype)
        else:  # (a stride's copy in memory already faulted in)
            self.bearings_t = work.take("bearings_t", src.shape, self.dtype)
            np.copyto(self.bearings_t, src, casting="same_kind")
        n = self.bearings_t.shape[1]
        self.batch_s = np.ascontiguousarray(batch_s, dtype=np.int32).reshape(-1)
        self.batch_u = np.ascontiguousarray(batch_u, dtype=self.dtype).reshape(-1)
        nb = len(self.batch_s)
        if nb * self.batch_size < n or (nb - 1) * self.batch_size >= max(n, 1):
            raise ValueError(f"{nb} batches of {batch_size} do not match {n} events")
        self.sigma = float(sigma)
        self.taps = gaussian_taps(self.sigma)
        self.radius = (len(self.taps) - 1) // 2
        self.n_px = self.width * self.height
        self.su, self.sv = self.width / (2 * math.pi), self.height / math.pi
        if global_blurred is not None:
            # the caller maintains B(I_G) and its sums incrementally (see pipelines/backend.GlobalMap)
            self.alpha = float(alpha)
            self.g_sum, self.g_sq = (float(v) for v in global_sums)
            self.gmap = np.ascontiguousarray(global_blurred, dtype=self.dtype)
        elif global_map is not None and (alpha != 0 or alpha_from_density is not None):
            g = blur_map(global_map, self.sigma)
            self.alpha = float(alpha)
            self.g_sum = float(g.sum())
            self.g_sq = float(np.sum(g * g))
            self.gmap = np.ascontiguousarray(g, dtype=self.dtype)
        else:
            self.alpha, self.g_sum, self.g_sq = 0.0, 0.0, 0.0
            self.gmap = np.zeros((1, 1), dtype=self.dtype)
        self._k = _iwe_kernels(_ti_dtype(self.dtype), self.degree, num_threads() == 1)
        order = self.degree + 1
        # written whole by the kernels before they are read (np.zeros of arrays this size is a memset per window,
        # ~2 ms for a million events: the allocator reuses freed blocks rather than fresh zero pages); from ``work``
        # when given (VoteWork: kept between instances)
        self._work = work
        take = work.take if work is not None else (lambda name, shape, dtype: np.empty(shape, dtype))
        self._jac = take("jac", (nb, order, 3, 3), self.dtype)
        self._rot = take("rot", (nb, 3, 3), self.dtype)  # the batches' poses
        # the knot intervals the batches reach, [lo, hi), and their spline segments (Omega_k, N_k) by control pose
        hi = int(self.batch_s.max()) + self.degree + 1 if nb else 1
        self._segments = (int(self.batch_s.min()) + 1 if nb else 1, hi, take("segment_log", (hi, 3), self.dtype),
                          take("segment_jr", (hi, 3, 3), self.dtype))
        self._bbox = take("bbox", (nb, 4), np.int32)
        self._gb = take("gb", (nb, order, 3), self.dtype)
        self.last_window = None  # (r0, c0, bh, bw, wrap) of the last evaluation, for inspection
        self._grad_bins = None  # (number of control poses, bincount index of each gradient term)
        self._density_ref = None  # (rho_g, lambda0) until alpha is set by the first evaluation
        if alpha_from_density is not None and self.g_sum > 0 and alpha_from_density[0] > 0:
            self._density_ref = (float(alpha_from_density[0]), float(alpha_from_density[1]))
            self.alpha = 1.0  # placeholder: the first evaluation sets it (the G terms are computed)
        # copies of the window buffer voted into by one parallel part each (the Taichi thread count, at most 8; a
        # chosen count must give every CPU task whole parts: runtime.check_parts)
        self.parts = check_parts(int(parts)) if parts else max(1, min(8, num_threads()))

    # -- helpers --
    def _window(self):
        """Buffer window from the batches' boxes: cyclic column interval covering all, rows, plus blur radius."""
        if len(self._bbox) == 0:
            return None
        w, r = self.width, self.radius
        a = self._bbox[:, 0].astype(np.int64)
        length = np.minimum(self._bbox[:, 1] - a, w)
        start = a % w
        # coverage of each column by the boxes: +1 at each start, -1 past each end, summed (bincount: np.add.at
        # cost 0.3 ms per evaluation for 2000 boxes)
        diff = np.bincount(start, minlength=2 * w + 1) - np.bincount(start + length, minlength=2 * w + 1)
        cover = np.cumsum(diff[:-1])
        occupied = (cover[:w] + cover[w:]) > 0
        cols = np.flatnonzero(occupied)
        gaps = np.diff(np.append(cols, cols[0] + w)) - 1  # empty columns after each occupied one (cyclic)
        k = int(np.argmax(gaps))
        span = w - int(gaps[k])
        first = int(cols[(k + 1) % len(cols)])
        if span + 2 * r >= w:
            c0, bw, wrap = 0, w, 1
        else:
            c0, bw, wrap = (first - r) % w, span + 2 * r, 0
        r0 = max(int(self._bbox[:, 2].min()) - r, 0)
        r1 = min(int(self._bbox[:, 3].max()) + r, self.height - 1)
        return r0, c0, r1 - r0 + 1, bw, wrap

    def _vote(self, control_R, lambda0: float = -1.0, with_grad: bool = True):
        """Project the events at these control poses and vote I_L (unblurred) into the window buffer: (ctrl, window
        (r0, c0, bh, bw, wrap) or None, buffer (bh, bw), per-row stats (bh, 3): raw sum, event area when lambda0
        >= 0)."""
        ctrl = np.ascontiguousarray(control_R, dtype=self.dtype).reshape(-1, 3, 3)
        if len(self.batch_s) and self.batch_s.max() + self.degree >= len(ctrl):
            raise ValueError("batch supports reach beyond the control poses passed")
        if self.bearings_t.shape[1] == 0:
            self.last_window = None
            return ctrl, None, None, None
        k = self._k
        k["poses"](ctrl, self.batch_s, self.batch_u, self.bearings_t, self.batch_size, self.width, self.height,
                   self.su, self.sv, *self._segments, self._rot, self._jac, self._bbox, self.parts * PART_TASK,
                   int(with_grad))
        win = self._window()
        self.last_window = win
        if win is None:
            return ctrl, None, None, None
        r0, c0, bh, bw, wrap = win
        if self._work is None:
            votes = np.zeros((self.parts * bh, bw), dtype=self.dtype)  # calloc: zero pages, no pass over memory
            lmap = votes if self.parts == 1 else np.empty((bh, bw), dtype=self.dtype)  # one part: voted in place
        else:  # (a memset of rows already faulted in: cheaper than fresh zero pages)
            votes = self._work.take("votes", (self.parts * bh, bw), self.dtype, zero=True)
            lmap = votes if self.parts == 1 else self._work.take("lmap", (bh, bw), self.dtype)
        stats = np.empty((bh, 3))
        k["vote"](self._rot, self.bearings_t, self.batch_size, self.width, self.height, self.su, self.sv, c0, r0,
                  lambda0, votes, lmap, stats)
        return ctrl, win, lmap, stats

    def votes(self, control_R):
        """The raw local map I_L (bilinear votes, unblurred) of the events at these control poses on its window:
        (first row, column indices (modulo the width), votes (bh, bw)), None when no event lands in the map. The
        back-end settles each stride into the global map with it: the BA's own projection and vote. With ``work``
        the votes are a view of its arrays (valid until the next instance on it votes)."""
        _, win, lmap, _ = self._vote(control_R, with_grad=False)
        if win is None:
            return None
        r0, c0, _bh, bw, wrap = win
        return r0, (np.arange(bw) if wrap else (c0 + np.arange(bw)) % self.width), lmap

    def _forward(self, control_R):
        # the event area only at the first call (alpha from the density)
        ctrl, win, lmap, stats = self._vote(control_R, self._density_ref[1] if self._density_ref is not None else -1.0)
        if win is None:
            return ctrl, None, None, self._constant_var()
        r0, c0, bh, bw, wrap = win
        if self._density_ref is not None:  # the first evaluation: alpha from the density of this local map
            raw, area = stats[:, :2].sum(axis=0)
            rho_g, _ = self._density_ref
            self.alpha = float(raw / area / rho_g) if area > 0 else 0.0
            self._density_ref = None
        separable_blur(lmap, self.taps, wrap_cols=bool(wrap), out=lmap)
        self._k["stats"](lmap, self.gmap, self.alpha, r0, c0, stats, self.parts * PART_TASK)
        s_l, s_ll, s_lg = stats.sum(axis=0)
        mu = (s_l + self.alpha * self.g_sum) / self.n_px
        # sum over all px of (L + aG - mu)^2 = sum (aG - mu)^2 + sum_buf (L^2 + 2 L (aG - mu))
        base = self.alpha**2 * self.g_sq - 2 * self.alpha * mu * self.g_sum + self.n_px * mu * mu
        var = (base + s_ll + 2 * self.alpha * s_lg - 2 * mu * s_l) / self.n_px
        return ctrl, (r0, c0, bh, bw, wrap), (lmap, mu), float(var)

    def _centred(self, lmap: np.ndarray, mu: float, r0: int, c0: int) -> np.ndarray:
        """L + alpha G - mu on the window (a new array; vectorized numpy passes over the buffer)."""
        out = np.empty_like(lmap) if self._work is None else self._work.take("centred", lmap.shape, lmap.dtype)
        if self.alpha != 0:
            bh, bw = lmap.shape
            n1 = min(bw, self.gmap.shape[1] - c0)  # buffer columns before the seam, then from map column 0
            rows = self.gmap[r0:r0 + bh]
            np.multiply(rows[:, c0:c0 + n1], self.dtype.type(self.alpha), out=out[:, :n1])
            np.multiply(rows[:, :bw - n1], self.dtype.type(self.alpha), out=out[:, n1:])
            out += lmap
        else:
            out[...] = lmap
        out -= self.dtype.type(mu)
        return out

    def _constant_var(self):
        """Variance without local votes (no events, or none in the map)."""
        if self._density_ref is not None:  # an empty local map has no density: alpha 0
            self.alpha, self._density_ref = 0.0, None
        mu = self.alpha * self.g_sum / self.n_px
        return float((self.alpha**2 * self.g_sq - self.n_px * mu * mu) / self.n_px)

    # -- public --
    def cost(self, control_R) -> float:
        """Variance of the panoramic IWE for these control poses."""
        return self._forward(control_R)[3]

    def cost_and_grad(self, control_R) -> tuple[float, np.ndarray]:
        """(variance, d variance / d delta (M, 3) float64) for left updates R_k <- exp(delta_k) R_k."""
        ctrl, win, maps, var = self._forward(control_R)
        grad = np.zeros((len(ctrl), 3))
        if win is None:
            return var, grad
        r0, c0, bh, bw, wrap = win
        wmap = self._centred(*maps, r0, c0)
        wmap = separable_blur(wmap, self.taps, wrap_cols=bool(wrap), out=wmap)  # W = B(L + alpha G - mu)
        self._k["gradient"](wmap, r0, c0, self._rot, self.bearings_t, self._jac, self.batch_size, self.width,
                            self.height, self.su, self.sv, self._gb, self.parts * PART_TASK)
        # out[b, k] adds to control pose batch_s[b] + k: one bincount over (pose, axis) bins
        order = self.degree + 1
        if self._grad_bins is None or self._grad_bins[0] != len(ctrl):
            bins = ((self.batch_s[:, None, None] + np.arange(order)[None, :, None]) * 3 + np.arange(3)).reshape(-1)
            self._grad_bins = (len(ctrl), bins)
        flat = np.bincount(self._grad_bins[1], self._gb.reshape(-1).astype(np.float64), minlength=3 * len(ctrl))
        grad += flat.reshape(-1, 3)
        grad *= 2.0 / self.n_px
        return var, grad

    def local_box(self, control_R):
        """(first row, column indices, blurred local map B(I_L) on that box) at these control poses; None when no
        event lands in the map. The box only: a crop of a large map costs no full-size array."""
        _, win, maps, _ = self._forward(control_R)
        if win is None:
            return None
        r0, c0, _bh, bw, _ = win
        return r0, (c0 + np.arange(bw)) % self.width, maps[0]

    def local_map(self, control_R) -> np.ndarray:
        """Full-size blurred local map B(I_L) of this window's events at these control poses (inspection, tests)."""
        box = self.local_box(control_R)
        out = np.zeros((self.height, self.width))
        if box is not None:
            r0, cols, lmap = box
            out[r0 : r0 + len(lmap)][:, cols] = lmap
        return out
