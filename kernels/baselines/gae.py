"""CMax-GAE (Kim & Kim RA-L 2021) math: the joint objective over (omega, dR) and the view of the global event map.

View: a virtual pinhole camera twice as wide and high as the sensor, same focal lengths, principal point shifted by
(W/2, H/2), looking along the current pose R (camera -> world). Event k (unit-depth bearing b_k, dt_k = t_k - t_ref)
is warped to t_ref by omega and rotated by the increment dR = exp(phi):
    X_k = exp(phi) exp(omega dt_k) b_k,   p_k = K' X_k / z  (pinhole)
I_L = bilinear votes of the p_k (in-bounds neighbours only), G = the (blurred) view of past events I_G, and
    C(omega, phi) = (1 / Np) sum_px (I_L + G)^2        (mean square, paper Eq. 6; Np = 4 W H)
    dC/dp_k = (2 / Np) sum_{n in nbrs(k)} (I_L + G)(n) dw_kn/dp_k
with dX/dphi = -[X]x Jl(phi) and dX/domega = exp(phi) (-[y]x Jl(omega dt) dt), y = exp(omega dt) b. The self term
sum_px I_L^2 is evaluated as sum_k sum_n w_kn I_L(n), so one evaluation costs O(events) (the view is never scanned:
touched pixels are cleared again after the pass) and sum_px G^2 is a per-interval constant computed on the host.

The global map is a fixed-size equirectangular histogram of past events on the unit sphere (``vote_map`` of world
bearings); ``render_sphere`` splats its cells inside the view (rows/columns box from ``footprint_bbox``) bilinearly.
Kernels per dtype (f32 production, f64 for finite differences); evaluation and rendering loops are serial (no float
atomics), so a run is reproducible bit for bit.
``objective_numpy`` and ``render_sphere_numpy`` are the float64 twins.
"""

import functools
import math

import numpy as np

from ti_cmax import so3

from ti_cmax.kernels import bilinear
from ti_cmax.kernels.bilinear import ADD, ATOMIC, CLEAR, bilinear_funcs
from ti_cmax.kernels.pano import _ti_dtype
from ti_cmax.kernels.runtime import ensure_init, ti
from ti_cmax.kernels.so3 import so3_funcs

_STORE = 15  # per event: u, v, valid, du/dparams (6), dv/dparams (6)


def view_K(K: np.ndarray, width: int, height: int) -> np.ndarray:
    """Intrinsics of the 2W x 2H view around the camera (same focal lengths, centre shifted by (W/2, H/2))."""
    Kv = np.array(K, dtype=np.float64)
    Kv[0, 1] = 0.0
    Kv[0, 2] += width / 2
    Kv[1, 2] += height / 2
    return Kv


# ----------------------------------------------------------------------------------------------------------------
# numpy twins
# ----------------------------------------------------------------------------------------------------------------
def _cell_directions(rows, cols, w, h):
    lon = (cols - w / 2) * 2 * np.pi / w
    lat = (rows - h / 2) * np.pi / h
    return np.stack([np.cos(lat) * np.sin(lon), np.sin(lat), np.cos(lat) * np.cos(lon)], -1)


def render_sphere_numpy(hist, R, Kv, vw, vh) -> np.ndarray:
    """Twin of ``render_sphere`` over the whole histogram: bilinear splats of the cells seen by the view."""
    hist = np.asarray(hist, dtype=np.float64)
    h, w = hist.shape
    jj, ii = np.nonzero(hist)
    c = _cell_directions(jj.astype(float), ii.astype(float), w, h) @ np.asarray(R, dtype=np.float64)
    z = c[:, 2]
    front = z > 1e-6
    c, z, wts = c[front], z[front], hist[jj, ii][front]
    px = Kv[0, 0] * c[:, 0] / z + Kv[0, 2]
    py = Kv[1, 1] * c[:, 1] / z + Kv[1, 2]
    return bilinear.vote_numpy(np.zeros((vh, vw)), px, py, wts)


def warp_numpy(bearings, dts, omega, phi, Kv):
    """Pixels p_k (N, 2) in the view, validity (z > 1e-6) and dp/d(omega, phi) (N, 2, 6), float64."""
    b = np.asarray(bearings, dtype=np.float64).reshape(-1, 3)
    dts = np.asarray(dts, dtype=np.float64)
    omega = np.asarray(omega, dtype=np.float64)
    phi = np.asarray(phi, dtype=np.float64)
    r1 = so3.exp(omega[None] * dts[:, None])
    y = np.einsum("nij,nj->ni", r1, b)
    e2 = so3.exp(phi)
    x = y @ e2.T
    z = x[:, 2]
    valid = z > 1e-6
    zs = np.where(valid, z, 1.0)
    px = Kv[0, 0] * x[:, 0] / zs + Kv[0, 2]
    py = Kv[1, 1] * x[:, 1] / zs + Kv[1, 2]
    dpdx = np.zeros((len(b), 2, 3))
    dpdx[:, 0, 0] = Kv[0, 0] / zs
    dpdx[:, 0, 2] = -Kv[0, 0] * x[:, 0] / zs ** 2
    dpdx[:, 1, 1] = Kv[1, 1] / zs
    dpdx[:, 1, 2] = -Kv[1, 1] * x[:, 1] / zs ** 2
    jl1 = np.stack([so3.left_jacobian(omega * dt) for dt in dts]) if len(b) else np.zeros((0, 3, 3))
    dx_dw = -np.einsum("ij,njk,nkl->nil", e2, so3.hat(y), jl1) * dts[:, None, None]
    dx_dphi = -so3.hat(x) @ so3.left_jacobian(phi)
    D = np.concatenate([dpdx @ dx_dw, dpdx @ dx_dphi], axis=2)
    return np.stack([px, py], 1), valid, D


def objective_numpy(bearings, dts, omega, phi, Kv, vw, vh, G):
    """Twin of ``GAEObjective.evaluate``: (C, dC/d(omega, phi) (6,), I_L) in float64."""
    p, valid, D = warp_numpy(bearings, dts, omega, phi, Kv)
    G = np.asarray(G, dtype=np.float64)
    p, D = p[valid], D[valid]
    il = bilinear.vote_numpy(np.zeros((vh, vw)), p[:, 0], p[:, 1])
    s = il + G
    np_ = vw * vh
    cost = float(np.sum(s * s)) / np_
    _, gu, gv = bilinear.sample_numpy(s, p[:, 0], p[:, 1])
    grad = 2.0 * (gu @ D[:, 0, :] + gv @ D[:, 1, :]) / np_
    return cost, grad, il


# ----------------------------------------------------------------------------------------------------------------
# Taichi kernels
# ----------------------------------------------------------------------------------------------------------------
@functools.cache
def _kernels(dtype):
    s3 = so3_funcs(dtype)
    bl = bilinear_funcs(dtype)
    vec3 = ti.types.vector(3, dtype)

    @ti.func
    def c(x):
        return ti.cast(x, dtype)

    @ti.kernel
    def k_eval(b: ti.types.ndarray(dtype=dtype, ndim=2), dts: ti.types.ndarray(dtype=dtype, ndim=1), n: ti.i32,
               prm: ti.types.ndarray(dtype=dtype, ndim=1), kv: ti.types.ndarray(dtype=dtype, ndim=1),
               G: ti.types.ndarray(dtype=dtype, ndim=2), il: ti.types.ndarray(dtype=dtype, ndim=2),
               st: ti.types.ndarray(dtype=dtype, ndim=2), out: ti.types.ndarray(dtype=dtype, ndim=1)):
        vh = il.shape[0]
        vw = il.shape[1]
        omega = vec3(prm[0], prm[1], prm[2])
        phi = vec3(prm[3], prm[4], prm[5])
        e2, jl2 = s3.exp_jl(phi)
        fx, fy, cx, cy = kv[0], kv[1], kv[2], kv[3]
        # pass 1: warp, derivatives, votes
        ti.loop_config(serialize=True)
        for k in range(n):
            bk = vec3(b[k, 0], b[k, 1], b[k, 2])
            dt = dts[k]
            e1, jl1 = s3.exp_jl(omega * dt)
            y = e1 @ bk
            x = e2 @ y
            st[k, 2] = c(0.0)
            if x[2] > c(1e-6):
                iz = c(1.0) / x[2]
                pu = fx * x[0] * iz + cx
                pv = fy * x[1] * iz + cy
                a = vec3(fx * iz, 0, -fx * x[0] * iz * iz)
                bb = vec3(0, fy * iz, -fy * x[1] * iz * iz)
                dxw = -(e2 @ s3.hat(y) @ jl1) * dt
                dxp = -(s3.hat(x) @ jl2)
                du_w = dxw.transpose() @ a
                du_p = dxp.transpose() @ a
                dv_w = dxw.transpose() @ bb
                dv_p = dxp.transpose() @ bb
                st[k, 0] = pu
                st[k, 1] = pv
                st[k, 2] = c(1.0)
                for q in ti.static(range(3)):
                    st[k, 3 + q] = du_w[q]
                    st[k, 6 + q] = du_p[q]
                    st[k, 9 + q] = dv_w[q]
                    st[k, 12 + q] = dv_p[q]
                bl.vote(il, pu, pv, c(1.0), ATOMIC)
        # pass 2: cost and gradient
        cost = c(0.0)
        g = ti.Vector([c(0.0)] * 6)
        ti.loop_config(serialize=True)
        for k in range(n):
            if st[k, 2] > c(0.5):
                i0, j0, fu, fv = bl.split(st[k, 0], st[k, 1])
                oka, okb = bl.col_ok(i0, vw)
                a_l = bl.gather(il, 0, vh, j0, i0, i0 + 1, oka, okb, -1)
                a_g = bl.gather(G, 0, vh, j0, i0, i0 + 1, oka, okb, -1)
                val, _, _ = bl.interp(a_l + c(2.0) * a_g, fu, fv)
                _, gu, gv = bl.interp(a_l + a_g, fu, fv)
                cost += val
                for q in ti.static(range(6)):
                    g[q] += c(2.0) * (gu * st[k, 3 + q] + gv * st[k, 9 + q])
        out[0] = cost
        for q in ti.static(range(6)):
            out[1 + q] = g[q]
        # pass 3: clear the touched pixels for the next evaluation
        for k in range(n):
            if st[k, 2] > c(0.5):
                bl.vote(il, st[k, 0], st[k, 1], c(0.0), CLEAR)

    @ti.kernel
    def k_render(hist: ti.types.ndarray(ndim=2), r0: ti.i32, nr: ti.i32, c0: ti.i32, nc: ti.i32,
                 rt: ti.types.ndarray(dtype=dtype, ndim=2), kv: ti.types.ndarray(dtype=dtype, ndim=1),
                 out: ti.types.ndarray(dtype=dtype, ndim=2)):
        h = hist.shape[0]
        w = hist.shape[1]
        # serial: a parallel loop needs float atomics, whose summation order varies run to run (CMax-GAE gave
        # 0.35-1.6 deg on the same input); serial plain adds make the baseline reproducible
        ti.loop_config(serialize=True)
        for jr, ic in ti.ndrange(nr, nc):
            j = r0 + jr
            i = (c0 + ic) % w
            val = c(hist[j, i])
            if val != 0:
                lon = (c(i) - c(0.5) * c(w)) * c(2 * math.pi) / c(w)
                lat = (c(j) - c(0.5) * c(h)) * c(math.pi) / c(h)
                d = vec3(ti.cos(lat) * ti.sin(lon), ti.sin(lat), ti.cos(lat) * ti.cos(lon))
                x = vec3(0, 0, 0)
                for p, q in ti.static(ti.ndrange(3, 3)):
                    x[p] += rt[p, q] * d[q]
                if x[2] > c(1e-6):
                    bl.vote(out, kv[0] * x[0] / x[2] + kv[2], kv[1] * x[1] / x[2] + kv[3], val, ADD)

    return k_eval, k_render


class GAEObjective:
    """C(omega, phi) of one interval (see the module docstring) with reusable buffers; ``evaluate`` -> (C, grad)."""

    def __init__(self, Kv: np.ndarray, vw: int, vh: int, dtype=np.float32):
        ensure_init()
        self.dtype = np.dtype(dtype)
        self.kv = np.array([Kv[0, 0], Kv[1, 1], Kv[0, 2], Kv[1, 2]], self.dtype)
        self.vw, self.vh = int(vw), int(vh)
        self.il = np.zeros((self.vh, self.vw), self.dtype)
        self.G = np.zeros((self.vh, self.vw), self.dtype)
        self.g2 = 0.0
        self.b = np.zeros((0, 3), self.dtype)
        self.dts = np.zeros(0, self.dtype)
        self.store = np.zeros((1, _STORE), self.dtype)
        self.evaluations = 0

    def set_interval(self, bearings, dts, G=None) -> None:
        self.b = np.ascontiguousarray(np.asarray(bearings).reshape(-1, 3), dtype=self.dtype)
        self.dts = np.ascontiguousarray(dts, dtype=self.dtype)
        if len(self.store) < len(self.b):
            self.store = np.zeros((max(len(self.b), 2 * len(self.store)), _STORE), self.dtype)
        if G is None:
            self.G[:] = 0
        else:
            self.G[:] = G
        self.g2 = float(np.sum(np.square(self.G, dtype=np.float64)))

    def evaluate(self, omega, phi):
        prm = np.concatenate([np.asarray(omega, float), np.asarray(phi, float)]).astype(self.dtype)
        out = np.zeros(7, self.dtype)
        _kernels(_ti_dtype(self.dtype))[0](self.b, self.dts, len(self.b), prm, self.kv, self.G, self.il,
                                             self.store, out)
        self.evaluations += 1
        np_ = self.vw * self.vh
        return (self.g2 + float(out[0])) / np_, out[1:].astype(np.float64) / np_


def render_sphere(hist, R, Kv, vw, vh, bbox, dtype=np.float32) -> np.ndarray:
    """Taichi: splat the histogram cells inside ``bbox`` (rows [r0, r1), cyclic columns [c0, c0 + nc)) seen by the
    view (pose R, intrinsics Kv, vw x vh) bilinearly into a new (vh, vw) image."""
    ensure_init()
    dtype = np.dtype(dtype)
    out = np.zeros((vh, vw), dtype)
    r0, r1, c0, nc = bbox
    if r1 > r0 and nc > 0:
        kv = np.array([Kv[0, 0], Kv[1, 1], Kv[0, 2], Kv[1, 2]], dtype)
        _kernels(_ti_dtype(dtype))[1](hist, int(r0), int(r1 - r0), int(c0), int(nc),
                                      np.ascontiguousarray(np.asarray(R).T, dtype), kv, out)
    return out
