"""RTPT (Reinbacher et al. ICCP 2017) math: Gauss-Newton tracking of an event packet against the edge map, map update.

Map: two equirectangular counters (h, w) per CONVENTIONS.md, O (triggered events: bilinear votes of tracked events)
and N (possible occurrences: +1 for every map point inside the camera's field of view at each packet). The edge map
is m = min(O / N, 1) (0 where N = 0) and M(u, v) its bilinear interpolation. Like the original's bounded map
image (cylindrical there, equirectangular here, as in the paper's benchmark) the map does NOT wrap in u: an event's
column is taken relative to the column of the camera centre (R e_z), unwrapped to within half a turn of it, and
columns outside [0, w) read as 0 and receive no votes. A view that straddles the map's left/right border (lon =
+-180 deg) therefore sees nothing past it: this is what makes RTPT lose track there.

Tracking cost of a packet (paper Eq. 4) at the packet rotation R (one rotation for all events of the packet):
    E(R) = 1/2 sum_k r_k^2,   r_k = 1 - M(pi(R b_k))
Right perturbation R <- R exp(delta): dX = -R [b]x delta, so J_k = b_k x (R^T dr_k/dX). Gauss-Newton / Levenberg-
Marquardt step (J^T J + lambda I) delta = -J^T r; with momentum ``accel`` the applied step is
delta + accel * previous applied step (heavy ball across the iterations of one packet).

Kernels are built per dtype (f32 production, f64 for finite-difference checks) and run serially over the events of
one packet (1500 by default): no float atomics (bit-reproducible) and one launch per packet for all iterations.
``normal_equations_numpy``, ``track_numpy``, ``update_map_numpy`` are the float64 twins (test oracles).
"""

import functools
import math

import numpy as np

from ti_cmax import so3

from ti_cmax.kernels import bilinear
from ti_cmax.kernels.bilinear import ATOMIC, bilinear_funcs
from ti_cmax.kernels.pano import _proj_funcs, _ti_dtype, equirect_numpy
from ti_cmax.kernels.runtime import ensure_init, ti
from ti_cmax.kernels.so3 import so3_funcs


# ----------------------------------------------------------------------------------------------------------------
# host-side geometry shared with CMax-GAE
# ----------------------------------------------------------------------------------------------------------------
def view_border_rays(K: np.ndarray, width: int, height: int, samples: int = 16) -> np.ndarray:
    """Unit-depth rays (M, 3) through the border of the pixel rectangle [0, width-1] x [0, height-1] of camera K."""
    s = np.linspace(0.0, 1.0, samples, endpoint=False)
    xs = np.concatenate([s * (width - 1), np.full_like(s, width - 1), (1 - s) * (width - 1), np.zeros_like(s)])
    ys = np.concatenate([np.zeros_like(s), s * (height - 1), np.full_like(s, height - 1), (1 - s) * (height - 1)])
    pix = np.stack([xs, ys, np.ones_like(xs)], 1)
    return pix @ np.linalg.inv(K).T


def footprint_bbox(R: np.ndarray, rays: np.ndarray, pano_w: int, pano_h: int, margin: int = 2):
    """Rows [r0, r1) and cyclic columns [c0, c0 + nc) of a w x h equirectangular grid that cover the view whose
    border rays (camera frame, from ``view_border_rays``) are rotated by R (camera -> world). The view must see
    less than a hemisphere; a pole inside the view gives all columns up to that pole."""
    xw = rays @ np.asarray(R, dtype=np.float64).T
    u, v = equirect_numpy(xw, pano_w, pano_h)
    centre = np.asarray(R, dtype=np.float64)[:, 2]
    uc, vc = equirect_numpy(centre[None], pano_w, pano_h)
    r0 = int(np.floor(v.min())) - margin
    r1 = int(np.ceil(v.max())) + margin + 1
    # a pole is inside the view when the border circles it: the unwrapped longitudes then span a full turn
    du = (u - uc[0] + pano_w / 2) % pano_w - pano_w / 2
    jumps = np.abs(np.diff(np.concatenate([du, du[:1]])))
    around_pole = np.any(jumps > pano_w / 2)
    if around_pole:
        if vc[0] < pano_h / 2:
            r0 = 0
        else:
            r1 = pano_h
        return max(r0, 0), min(r1, pano_h), 0, pano_w
    c0 = int(np.floor(uc[0] + du.min())) - margin
    nc = int(np.ceil(uc[0] + du.max())) + margin + 1 - c0
    return max(r0, 0), min(r1, pano_h), c0 % pano_w, min(nc, pano_w)


def unwrap_about_centre_numpy(u, R, w, h):
    """Columns relative to the camera centre's column (R e_z), unwrapped to (uc - w/2, uc + w/2]: the map is a
    bounded image, so a view straddling lon = +-180 deg reaches past its left/right border."""
    uc, _ = equirect_numpy(np.asarray(R, dtype=np.float64)[:, 2][None], w, h)
    return uc[0] + (u - uc[0] + w / 2) % w - w / 2


def _edge_map_np(O, N):
    O = np.asarray(O, dtype=np.float64)
    N = np.asarray(N, dtype=np.float64)
    return np.where(N > 0, np.minimum(O / np.maximum(N, 1e-300), 1.0), 0.0)


def edge_map(O, N) -> np.ndarray:
    """The probabilistic edge map M = min(O / N, 1) (0 where never observed), float32 (h, w)."""
    return _edge_map_np(O, N).astype(np.float32)


# ----------------------------------------------------------------------------------------------------------------
# numpy twins
# ----------------------------------------------------------------------------------------------------------------
def normal_equations_numpy(bearings, R, O, N):
    """Twin of ``normal_equations``: (cost 1/2 sum r^2, J^T J (3, 3), J^T r (3,), mean M) in float64."""
    b = np.asarray(bearings, dtype=np.float64).reshape(-1, 3)
    R = np.asarray(R, dtype=np.float64)
    m = _edge_map_np(O, N)
    h, w = m.shape
    xw = b @ R.T
    u, v = equirect_numpy(xw, w, h)
    u = unwrap_about_centre_numpy(u, R, w, h)
    val, du, dv = bilinear.sample_numpy(m, u, v)
    r = 1.0 - val
    x, y, z = xw[:, 0], xw[:, 1], xw[:, 2]
    rho2 = x * x + z * z
    rho = np.sqrt(rho2)
    r2 = rho2 + y * y
    ddu = (w / (2 * np.pi)) * np.stack([z / rho2, np.zeros_like(x), -x / rho2], 1)
    ddv = (h / np.pi) * np.stack([-x * y, rho2, -z * y], 1) / (rho * r2)[:, None]
    g = -(du[:, None] * ddu + dv[:, None] * ddv)  # dr/dX
    J = np.cross(b, g @ R)  # b x (R^T g)
    return 0.5 * float(r @ r), J.T @ J, J.T @ r, float(val.mean()) if len(val) else 0.0


def track_numpy(bearings, R0, O, N, iterations=10, lam=100.0, accel=0.4):
    """Twin of ``track``: LM iterations with momentum from R0; returns (R, cost before, cost after, mean M)."""
    R = np.asarray(R0, dtype=np.float64).copy()
    prev = np.zeros(3)
    c0 = None
    for _ in range(iterations):
        cost, A, g, _ = normal_equations_numpy(bearings, R, O, N)
        if c0 is None:
            c0 = cost
        step = -np.linalg.solve(A + lam * np.eye(3), g) + accel * prev
        R = R @ so3.exp(step)
        prev = step
    cost, _, _, q = normal_equations_numpy(bearings, R, O, N)
    return R, (cost if c0 is None else c0), cost, q


def update_map_numpy(bearings, R, O, N, K, cam_w, cam_h):
    """Twin of ``update_map``: bilinear votes of R b into O (no wrap), +1 in N at every map point whose direction
    projects (pinhole K, in front) into [0, cam_w - 1] x [0, cam_h - 1]. In place, float64 copies returned."""
    O = np.asarray(O, dtype=np.float64).copy()
    N = np.asarray(N, dtype=np.float64).copy()
    h, w = O.shape
    b = np.asarray(bearings, dtype=np.float64).reshape(-1, 3)
    xw = b @ np.asarray(R, dtype=np.float64).T
    u, v = equirect_numpy(xw, w, h)
    bilinear.vote_numpy(O, unwrap_about_centre_numpy(u, R, w, h), v)
    jj, ii = np.mgrid[0:h, 0:w].astype(np.float64)
    lon = (ii - w / 2) * 2 * np.pi / w
    lat = (jj - h / 2) * np.pi / h
    d = np.stack([np.cos(lat) * np.sin(lon), np.sin(lat), np.cos(lat) * np.cos(lon)], -1)
    c = d @ np.asarray(R, dtype=np.float64)  # R^T d
    z = c[..., 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        px = K[0, 0] * c[..., 0] / z + K[0, 2]
        py = K[1, 1] * c[..., 1] / z + K[1, 2]
    inside = (z > 0) & (px >= 0) & (px <= cam_w - 1) & (py >= 0) & (py <= cam_h - 1)
    N[inside] += 1
    return O, N


# ----------------------------------------------------------------------------------------------------------------
# Taichi kernels
# ----------------------------------------------------------------------------------------------------------------
@functools.cache
def _kernels(dtype):
    project, project_jacobian = _proj_funcs(dtype)
    s3 = so3_funcs(dtype)
    bl = bilinear_funcs(dtype)
    vec3 = ti.types.vector(3, dtype)
    mat3 = ti.types.matrix(3, 3, dtype)

    @ti.func
    def m_at(O: ti.template(), N: ti.template(), j, i):
        val = ti.cast(0.0, dtype)
        if i >= 0 and i < O.shape[1] and j >= 0 and j < O.shape[0]:
            n = ti.cast(N[j, i], dtype)
            if n > 0:
                val = ti.min(ti.cast(O[j, i], dtype) / n, ti.cast(1.0, dtype))
        return val

    @ti.func
    def unwrap(pu, uc, w):
        """Column of an event relative to the camera centre's column uc (bounded map, see the module docstring)."""
        half = ti.cast(0.5, dtype) * ti.cast(w, dtype)
        out = pu
        if pu - uc > half:
            out = pu - ti.cast(w, dtype)
        elif pu - uc <= -half:
            out = pu + ti.cast(w, dtype)
        return out

    @ti.func
    def centre_u(R, w, h, su, sv):
        pc, _ = project(vec3(R[0, 2], R[1, 2], R[2, 2]), w, h, su, sv)
        return pc

    @ti.func
    def normal(b: ti.template(), n, R, O: ti.template(), N: ti.template(), su, sv):
        """cost, J^T J, J^T r, sum M over the packet at rotation R (serial)."""
        w = O.shape[1]
        h = O.shape[0]
        cost = ti.cast(0.0, dtype)
        msum = ti.cast(0.0, dtype)
        A = mat3(0)
        g = vec3(0)
        uc = centre_u(R, w, h, su, sv)
        ti.loop_config(serialize=True)
        for k in range(n):
            bk = vec3(b[k, 0], b[k, 1], b[k, 2])
            x = R @ bk
            pu, pv = project(x, w, h, su, sv)
            i0, j0, fu, fv = bl.split(unwrap(pu, uc, w), pv)
            m4 = ti.Vector([m_at(O, N, j0, i0), m_at(O, N, j0, i0 + 1), m_at(O, N, j0 + 1, i0),
                            m_at(O, N, j0 + 1, i0 + 1)])
            val, dmu, dmv = bl.interp(m4, fu, fv)
            r = ti.cast(1.0, dtype) - val
            ddu, ddv = project_jacobian(x, su, sv)
            gx = -(dmu * ddu + dmv * ddv)
            J = bk.cross(R.transpose() @ gx)
            A += J.outer_product(J)
            g += J * r
            cost += ti.cast(0.5, dtype) * r * r
            msum += val
        return cost, A, g, msum

    @ti.kernel
    def k_normal(b: ti.types.ndarray(dtype=dtype, ndim=2), n: ti.i32, R: ti.types.ndarray(dtype=dtype, ndim=2),
                 O: ti.types.ndarray(ndim=2), N: ti.types.ndarray(ndim=2), su: dtype, sv: dtype,
                 out: ti.types.ndarray(dtype=dtype, ndim=1)):
        Rm = mat3(0)
        for i, j in ti.static(ti.ndrange(3, 3)):
            Rm[i, j] = R[i, j]
        cost, A, g, msum = normal(b, n, Rm, O, N, su, sv)
        out[0] = cost
        for i, j in ti.static(ti.ndrange(3, 3)):
            out[1 + 3 * i + j] = A[i, j]
        for i in ti.static(range(3)):
            out[10 + i] = g[i]
        out[13] = msum

    @ti.kernel
    def k_track(b: ti.types.ndarray(dtype=dtype, ndim=2), n: ti.i32, R: ti.types.ndarray(dtype=dtype, ndim=2),
                O: ti.types.ndarray(ndim=2), N: ti.types.ndarray(ndim=2), su: dtype, sv: dtype, iters: ti.i32,
                lam: dtype, accel: dtype, out: ti.types.ndarray(dtype=dtype, ndim=1)):
        """In place on R: ``iters`` LM steps with momentum; out = [cost before, cost after, sum M after]."""
        Rm = mat3(0)
        for i, j in ti.static(ti.ndrange(3, 3)):
            Rm[i, j] = R[i, j]
        prev = vec3(0)
        c0 = ti.cast(0.0, dtype)
        ti.loop_config(serialize=True)
        for it in range(iters):
            cost, A, g, msum = normal(b, n, Rm, O, N, su, sv)
            if it == 0:
                c0 = cost
            step = -((A + lam * ti.Matrix.identity(dtype, 3)).inverse() @ g) + accel * prev
            Rm = Rm @ s3.exp(step)
            prev = step
        cost, A, g, msum = normal(b, n, Rm, O, N, su, sv)
        if iters == 0:
            c0 = cost
        for i, j in ti.static(ti.ndrange(3, 3)):
            R[i, j] = Rm[i, j]
        out[0] = c0
        out[1] = cost
        out[2] = msum

    @ti.kernel
    def k_vote(b: ti.types.ndarray(dtype=dtype, ndim=2), n: ti.i32, R: ti.types.ndarray(dtype=dtype, ndim=2),
               O: ti.types.ndarray(ndim=2), su: dtype, sv: dtype):
        Rm = mat3(0)
        for i, j in ti.static(ti.ndrange(3, 3)):
            Rm[i, j] = R[i, j]
        w = O.shape[1]
        h = O.shape[0]
        uc = centre_u(Rm, w, h, su, sv)
        ti.loop_config(serialize=True)
        for k in range(n):
            x = Rm @ vec3(b[k, 0], b[k, 1], b[k, 2])
            pu, pv = project(x, w, h, su, sv)
            bl.vote(O, unwrap(pu, uc, w), pv, ti.cast(1.0, dtype), ATOMIC)

    @ti.kernel
    def k_fov(Rt: ti.types.ndarray(dtype=dtype, ndim=2), N: ti.types.ndarray(ndim=2), r0: ti.i32, nr: ti.i32,
              c0: ti.i32, nc: ti.i32, fx: dtype, fy: dtype, cx: dtype, cy: dtype, cam_w: ti.i32, cam_h: ti.i32):
        """N += 1 at every map point of rows [r0, r0 + nr), cyclic columns [c0, c0 + nc) seen by the camera."""
        w = N.shape[1]
        h = N.shape[0]
        Rm = mat3(0)
        for i, j in ti.static(ti.ndrange(3, 3)):
            Rm[i, j] = Rt[i, j]
        for jr, ic in ti.ndrange(nr, nc):
            j = r0 + jr
            i = (c0 + ic) % w
            lon = (ti.cast(i, dtype) - ti.cast(0.5, dtype) * ti.cast(w, dtype)) * ti.cast(2 * math.pi, dtype) / \
                ti.cast(w, dtype)
            lat = (ti.cast(j, dtype) - ti.cast(0.5, dtype) * ti.cast(h, dtype)) * ti.cast(math.pi, dtype) / \
                ti.cast(h, dtype)
            d = vec3(ti.cos(lat) * ti.sin(lon), ti.sin(lat), ti.cos(lat) * ti.cos(lon))
            c = Rm @ d
            if c[2] > 0:
                px = fx * c[0] / c[2] + cx
                py = fy * c[1] / c[2] + cy
                if px >= 0 and px <= ti.cast(cam_w - 1, dtype) and py >= 0 and py <= ti.cast(cam_h - 1, dtype):
                    N[j, i] += 1

    return k_normal, k_track, k_vote, k_fov


def _scales(shape):
    h, w = shape
    return w / (2 * math.pi), h / math.pi


def _prep(bearings, dtype):
    return np.ascontiguousarray(np.asarray(bearings).reshape(-1, 3), dtype=dtype)


def normal_equations(bearings, R, O, N, dtype=np.float32):
    """Taichi: (cost, J^T J, J^T r, mean M) of a packet at rotation R against the map counters O, N."""
    ensure_init()
    dtype = np.dtype(dtype)
    b = _prep(bearings, dtype)
    out = np.zeros(14, dtype)
    su, sv = _scales(O.shape)
    _kernels(_ti_dtype(dtype))[0](b, len(b), np.ascontiguousarray(R, dtype), O, N, su, sv, out)
    n = max(len(b), 1)
    return float(out[0]), out[1:10].reshape(3, 3).astype(np.float64), out[10:13].astype(np.float64), \
        float(out[13]) / n


def track(bearings, R0, O, N, iterations=10, lam=100.0, accel=0.4, dtype=np.float32):
    """Taichi: LM iterations with momentum from R0 in one launch -> (R, cost before, cost after, mean M after)."""
    ensure_init()
    dtype = np.dtype(dtype)
    b = _prep(bearings, dtype)
    R = np.ascontiguousarray(R0, dtype).copy()
    out = np.zeros(3, dtype)
    su, sv = _scales(O.shape)
    _kernels(_ti_dtype(dtype))[1](b, len(b), R, O, N, su, sv, int(iterations), float(lam), float(accel), out)
    return R.astype(np.float64), float(out[0]), float(out[1]), float(out[2]) / max(len(b), 1)


def update_map(bearings, R, O, N, K, cam_w, cam_h, bbox, dtype=np.float32):
    """Taichi, in place: votes of R b into O (no wrap), N += 1 on the camera's footprint inside ``bbox`` (rows
    [r0, r1), cyclic columns [c0, c0 + nc), from ``footprint_bbox``)."""
    ensure_init()
    dtype = np.dtype(dtype)
    b = _prep(bearings, dtype)
    k_normal, k_track, k_vote, k_fov = _kernels(_ti_dtype(dtype))
    su, sv = _scales(O.shape)
    Rc = np.ascontiguousarray(R, dtype)
    if len(b):
        k_vote(b, len(b), Rc, O, su, sv)
    r0, r1, c0, nc = bbox
    if r1 > r0 and nc > 0:
        k_fov(np.ascontiguousarray(np.asarray(R).T, dtype), N, int(r0), int(r1 - r0), int(c0), int(nc),
              float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]), int(cam_w), int(cam_h))
