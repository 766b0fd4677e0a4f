"""SMT trackers' hot loops (paper Sec. II-A, App. B), Taichi + numpy twins.

Measurement of event k (Eq. 1, linearized on the mapping EKFs' gradient map, same sign convention as
kernels/mapping.py): the map point of its sensor pixel moved from p_prev (previous event at that pixel, under the
pose estimated then) to p = p(R b_k); the brightness increment is predicted as

    z_hat = g(p_mid) . dp,   dp = p - p_prev (longitude wrapped),   p_mid = p_prev + dp / 2,

with g (and its 2x2 covariance P_g) bilinearly interpolated at p_mid, and compared with z = p_k C. Residual
r = p_k C - z_hat, variance S = sigma^2 + dp^T P_g dp (unmapped pixels keep the prior covariance, so they weigh
little by themselves). Measurements with |dp| above ``outlier_px`` or below ``min_disp_px`` are skipped, as in the
mapping EKF.

Left perturbation R <- exp(d) R (world frame, as the back-end): d z_hat / d d = (X' x g_X)^T with X' = R b,
g_X = e_u du/dX' + e_v dv/dX' and e = d z_hat / d p = g(p_mid) + (1/2) (d g / d p_mid)^T dp (the bilinear map's
slope included: it is what ties the pose to the map rather than only to the previous poses).

* :func:`project_prev` -- p_prev of each event from a pose history (the tracker's per-pixel memory stores the
  index of the pose of the previous event).
* :func:`ekf_accumulate` -- one pose: Huber-weighted normal equations H^T W H (6 values), H^T W r (3) and
  diagnostics, summed over a batch (serialized loop: reproducible).
* :func:`pf_loglik` -- many poses (particles): sum over the batch of log(N(r; 0, S) + floor) (parallel over
  particles, serial over events: reproducible).

Every kernel has a float64 numpy twin (``*_numpy``). f32 uses the polynomial atan2 of kernels/pano.
"""

import functools

import numpy as np

from . import bilinear
from .bilinear import bilinear_funcs
from .pano import _proj_funcs, equirect_numpy
from .runtime import ensure_init, ti
from .so3 import so3_funcs as _so3_funcs

# slots of the ekf_accumulate output
ACC = ("h00", "h01", "h02", "h11", "h12", "h22", "b0", "b1", "b2",
       "valid", "supported", "agree", "nis", "chi2", "ppred", "pred2")
N_ACC = len(ACC)
_SQRT_2PI = float(np.sqrt(2.0 * np.pi))


# ----------------------------------------------------------------------------------------------------------------
# numpy twins (float64 oracles)
# ----------------------------------------------------------------------------------------------------------------
def _project_jacobian_numpy(xw, width, height):
    x, y, z = xw[:, 0], xw[:, 1], xw[:, 2]
    rho2 = x * x + z * z
    rho = np.sqrt(rho2)
    r2 = rho2 + y * y
    su, sv = width / (2 * np.pi), height / np.pi
    du = su * np.stack([z / rho2, np.zeros_like(x), -x / rho2], 1)
    dv = sv * np.stack([-x * y, rho2, -z * y], 1) / (rho * r2)[:, None]
    return du, dv


def _measure_numpy(R, bearings, prev_uv, valid, pol, grad, cov, updates, contrast, sigma2, outlier_px,
                   min_disp_px):
    """Per-event (ok, r, S, H (n, 3), pred, support) for one pose R (float64)."""
    h, w = updates.shape
    xw = np.asarray(bearings, np.float64) @ np.asarray(R, np.float64).T
    u, v = equirect_numpy(xw, w, h)
    du = u - prev_uv[:, 0]
    dv = v - prev_uv[:, 1]
    du = np.where(du > 0.5 * w, du - w, np.where(du <= -0.5 * w, du + w, du))
    d2 = du * du + dv * dv
    ok = (np.asarray(valid) != 0) & (d2 <= outlier_px ** 2) & (d2 >= min_disp_px ** 2)
    mu = prev_uv[:, 0] + 0.5 * du
    mv = prev_uv[:, 1] + 0.5 * dv
    # g, P and the mapped weight bilinear at (mu, mv) (longitude wrapped, rows outside the map contribute nothing)
    g, gdu, gdv = bilinear.sample_numpy(grad, mu, mv, wrap_u=True)
    P = bilinear.sample_numpy(cov, mu, mv, wrap_u=True)[0]
    sup = bilinear.sample_numpy(updates > 0, mu, mv, wrap_u=True)[0]
    pred = g[:, 0] * du + g[:, 1] * dv
    S = sigma2 + du * du * P[:, 0] + 2 * du * dv * P[:, 1] + dv * dv * P[:, 2]
    r = np.asarray(pol, np.float64) * contrast - pred
    jdu, jdv = _project_jacobian_numpy(xw, w, h)
    # d z_hat / d p = g(p_mid) + (1/2) (d g / d p_mid)^T dp  (p_mid moves by half of p)
    eu = g[:, 0] + 0.5 * (du * gdu[:, 0] + dv * gdu[:, 1])
    ev = g[:, 1] + 0.5 * (du * gdv[:, 0] + dv * gdv[:, 1])
    gx = eu[:, None] * jdu + ev[:, None] * jdv
    H = np.cross(xw, gx)
    return ok, r, S, H, pred, sup


def project_prev_numpy(poses, prev_idx, bearings, width, height):
    """(n, 2) map point of each event's bearing under poses[prev_idx] (NaN where prev_idx < 0)."""
    idx = np.asarray(prev_idx, np.int64)
    out = np.full((len(idx), 2), np.nan)
    ok = idx >= 0
    if ok.any():
        xw = np.einsum("nij,nj->ni", np.asarray(poses, np.float64)[idx[ok]], np.asarray(bearings, np.float64)[ok])
        out[ok, 0], out[ok, 1] = equirect_numpy(xw, width, height)
    return out


def ekf_accumulate_numpy(R, bearings, prev_uv, valid, pol, grad, cov, updates, contrast, sigma, outlier_px,
                         min_disp_px, huber):
    """Twin of :func:`ekf_accumulate` (float64): returns the N_ACC sums."""
    ok, r, S, H, pred, sup = _measure_numpy(R, bearings, prev_uv, valid, pol, grad, cov, updates, contrast,
                                            sigma * sigma, outlier_px, min_disp_px)
    out = np.zeros(N_ACC)
    nr = np.abs(r) / np.sqrt(S)
    wt = np.where(nr <= huber, 1.0, huber / np.maximum(nr, 1e-300)) / S
    wt = np.where(ok, wt, 0.0)
    hw = H * wt[:, None]
    hh = hw.T @ H
    out[0:6] = hh[0, 0], hh[0, 1], hh[0, 2], hh[1, 1], hh[1, 2], hh[2, 2]
    out[6:9] = hw.T @ r
    supported = ok & (sup >= 0.5)
    out[9] = ok.sum()
    out[10] = supported.sum()
    out[11] = (supported & (pred * np.asarray(pol, np.float64) > 0)).sum()
    out[12] = np.sum(np.where(supported, r * r / S, 0.0))
    out[13] = np.sum(np.where(ok, np.minimum(nr, huber) ** 2, 0.0))
    out[14] = np.sum(np.where(supported, pred * np.asarray(pol, np.float64), 0.0))
    out[15] = np.sum(np.where(supported, pred * pred, 0.0))
    return out


def pf_loglik_numpy(particles, bearings, prev_uv, valid, pol, grad, cov, updates, contrast, sigma, outlier_px,
                    min_disp_px, floor):
    """Twin of :func:`pf_loglik`: (N,) sum over events of log(N(r; 0, S) + floor) per particle (float64)."""
    out = np.zeros(len(particles))
    for i, R in enumerate(np.asarray(particles, np.float64)):
        ok, r, S, _, _, _ = _measure_numpy(R, bearings, prev_uv, valid, pol, grad, cov, updates, contrast,
                                           sigma * sigma, outlier_px, min_disp_px)
        dens = np.exp(-0.5 * r * r / S) / (_SQRT_2PI * np.sqrt(S))
        out[i] = np.sum(np.where(ok, np.log(dens + floor), 0.0))
    return out


# ----------------------------------------------------------------------------------------------------------------
# Taichi kernels
# ----------------------------------------------------------------------------------------------------------------
@functools.cache
def _kernels(dtype):
    project, project_jacobian = _proj_funcs(dtype)
    bl = bilinear_funcs(dtype)
    vec3 = ti.types.vector(3, dtype)
    mat3 = ti.types.matrix(3, 3, dtype)

    @ti.func
    def measure(R, b, u0, v0, pol, grad: ti.template(), cov: ti.template(), updates: ti.template(),
                width, height, su, sv, contrast, sigma2, outlier2, min2):
        """(ok, r, S, H, pred, support) of one event under pose R (see module doc)."""
        x = R @ b
        pu, pv = project(x, width, height, su, sv)
        wf = ti.cast(width, dtype)
        du = pu - u0
        dv = pv - v0
        if du > ti.cast(0.5, dtype) * wf:
            du -= wf
        elif du <= -ti.cast(0.5, dtype) * wf:
            du += wf
        d2 = du * du + dv * dv
        ok = 0
        r = ti.cast(0.0, dtype)
        S = ti.cast(1.0, dtype)
        H = vec3(0, 0, 0)
        pred = ti.cast(0.0, dtype)
        sup = ti.cast(0.0, dtype)
        if d2 <= outlier2 and d2 >= min2:
            ok = 1
            mu = u0 + ti.cast(0.5, dtype) * du
            mv = v0 + ti.cast(0.5, dtype) * dv
            i0, j0, fu, fv = bl.split(mu, mv)
            ia, ib = bl.wrap_cols(i0, width)  # mu in (-w/2, 3w/2)
            gu, gu_u, gu_v = bl.interp(bl.gather(grad, 0, height, j0, ia, ib, 1, 1, 0), fu, fv)  # g_u, d/du, d/dv
            gv, gv_u, gv_v = bl.interp(bl.gather(grad, 0, height, j0, ia, ib, 1, 1, 1), fu, fv)
            p00, _, _ = bl.interp(bl.gather(cov, 0, height, j0, ia, ib, 1, 1, 0), fu, fv)
            p01, _, _ = bl.interp(bl.gather(cov, 0, height, j0, ia, ib, 1, 1, 1), fu, fv)
            p11, _, _ = bl.interp(bl.gather(cov, 0, height, j0, ia, ib, 1, 1, 2), fu, fv)
            mapped = ti.cast(bl.gather(updates, 0, height, j0, ia, ib, 1, 1, -1) > 0, dtype)
            sup, _, _ = bl.interp(mapped, fu, fv)
            pred = gu * du + gv * dv
            S = sigma2 + du * du * p00 + ti.cast(2.0, dtype) * du * dv * p01 + dv * dv * p11
            r = ti.cast(pol, dtype) * contrast - pred
            jdu, jdv = project_jacobian(x, su, sv)
            eu = gu + ti.cast(0.5, dtype) * (du * gu_u + dv * gv_u)
            ev = gv + ti.cast(0.5, dtype) * (du * gu_v + dv * gv_v)
            gx = eu * jdu + ev * jdv
            H = x.cross(gx)
        return ok, r, S, H, pred, sup

    @ti.kernel
    def k_project_prev(poses: ti.types.ndarray(dtype=mat3, ndim=1),
                       prev_idx: ti.types.ndarray(dtype=ti.i32, ndim=1),
                       bearings: ti.types.ndarray(dtype=vec3, ndim=1), width: ti.i32, height: ti.i32, su: dtype,
                       sv: dtype, out: ti.types.ndarray(dtype=dtype, ndim=2)):
        for e in range(bearings.shape[0]):
            k = prev_idx[e]
            if k >= 0:
                pu, pv = project(poses[k] @ bearings[e], width, height, su, sv)
                out[e, 0] = pu
                out[e, 1] = pv
            else:
                out[e, 0] = ti.cast(0.0, dtype)
                out[e, 1] = ti.cast(0.0, dtype)

    @ti.kernel
    def k_accumulate(R: ti.types.ndarray(dtype=mat3, ndim=1), bearings: ti.types.ndarray(dtype=vec3, ndim=1),
                     prev_uv: ti.types.ndarray(dtype=dtype, ndim=2), valid: ti.types.ndarray(dtype=ti.i8, ndim=1),
                     pol: ti.types.ndarray(dtype=ti.i8, ndim=1), grad: ti.types.ndarray(dtype=dtype, ndim=3),
                     cov: ti.types.ndarray(dtype=dtype, ndim=3), updates: ti.types.ndarray(dtype=ti.i32, ndim=2),
                     width: ti.i32, height: ti.i32, su: dtype, sv: dtype, contrast: dtype, sigma2: dtype,
                     outlier2: dtype, min2: dtype, huber: dtype, out: ti.types.ndarray(dtype=ti.f64, ndim=1)):
        rot = R[0]
        ti.loop_config(serialize=True)
        for e in range(bearings.shape[0]):
            if valid[e] != 0:
                ok, r, S, H, pred, sup = measure(rot, bearings[e], prev_uv[e, 0], prev_uv[e, 1], pol[e], grad, cov,
                                                 updates, width, height, su, sv, contrast, sigma2, outlier2, min2)
                if ok == 1:
                    nr = ti.abs(r) / ti.sqrt(S)
                    wt = ti.cast(1.0, dtype) / S
                    if nr > huber:
                        wt *= huber / nr
                    h0 = ti.cast(H[0], ti.f64)
                    h1 = ti.cast(H[1], ti.f64)
                    h2 = ti.cast(H[2], ti.f64)
                    w64 = ti.cast(wt, ti.f64)
                    r64 = ti.cast(r, ti.f64)
                    out[0] += w64 * h0 * h0
                    out[1] += w64 * h0 * h1
                    out[2] += w64 * h0 * h2
                    out[3] += w64 * h1 * h1
                    out[4] += w64 * h1 * h2
                    out[5] += w64 * h2 * h2
                    out[6] += w64 * h0 * r64
                    out[7] += w64 * h1 * r64
                    out[8] += w64 * h2 * r64
                    out[9] += 1.0
                    out[13] += ti.cast(ti.min(nr, huber) ** 2, ti.f64)
                    if sup >= 0.5:
                        out[10] += 1.0
                        out[12] += ti.cast(r * r / S, ti.f64)
                        out[14] += ti.cast(pred * ti.cast(pol[e], dtype), ti.f64)
                        out[15] += ti.cast(pred * pred, ti.f64)
                        if pred * ti.cast(pol[e], dtype) > 0:
                            out[11] += 1.0

    @ti.kernel
    def k_loglik(particles: ti.types.ndarray(dtype=mat3, ndim=1), bearings: ti.types.ndarray(dtype=vec3, ndim=1),
                 prev_uv: ti.types.ndarray(dtype=dtype, ndim=2), valid: ti.types.ndarray(dtype=ti.i8, ndim=1),
                 pol: ti.types.ndarray(dtype=ti.i8, ndim=1), grad: ti.types.ndarray(dtype=dtype, ndim=3),
                 cov: ti.types.ndarray(dtype=dtype, ndim=3), updates: ti.types.ndarray(dtype=ti.i32, ndim=2),
                 width: ti.i32, height: ti.i32, su: dtype, sv: dtype, contrast: dtype, sigma2: dtype,
                 outlier2: dtype, min2: dtype, floor: dtype, inv_sqrt_2pi: dtype,
                 out: ti.types.ndarray(dtype=ti.f64, ndim=1)):
        ti.loop_config(block_dim=4)  # few, heavy iterations: spread them over the threads
        for i in range(particles.shape[0]):
            rot = particles[i]
            acc = ti.cast(0.0, ti.f64)
            for e in range(bearings.shape[0]):
                if valid[e] != 0:
                    ok, r, S, H, pred, sup = measure(rot, bearings[e], prev_uv[e, 0], prev_uv[e, 1], pol[e], grad,
                                                     cov, updates, width, height, su, sv, contrast, sigma2,
                                                     outlier2, min2)
                    if ok == 1:
                        dens = ti.exp(-ti.cast(0.5, dtype) * r * r / S) * inv_sqrt_2pi / ti.sqrt(S)
                        acc += ti.cast(ti.log(dens + floor), ti.f64)
            out[i] = acc

    f64 = ti.f64
    mat3d = ti.types.matrix(3, 3, f64)
    vec3d = ti.types.vector(3, f64)
    so3d = _so3_funcs(f64)

    @ti.kernel
    def k_ekf_track(hist: ti.types.ndarray(dtype=mat3, ndim=1), hist64: ti.types.ndarray(dtype=mat3d, ndim=1),
                    mids: ti.types.ndarray(dtype=f64, ndim=1), b0: ti.i32, b1: ti.i32, batch_size: ti.i32,
                    bearings: ti.types.ndarray(dtype=vec3, ndim=1),
                    prev_batch: ti.types.ndarray(dtype=ti.i32, ndim=1),
                    pol: ti.types.ndarray(dtype=ti.i8, ndim=1), grad: ti.types.ndarray(dtype=dtype, ndim=3),
                    cov: ti.types.ndarray(dtype=dtype, ndim=3), updates: ti.types.ndarray(dtype=ti.i32, ndim=2),
                    width: ti.i32, height: ti.i32, su: dtype, sv: dtype, contrast: dtype, sigma2: dtype,
                    outlier2: dtype, min2: dtype, huber: dtype, q_rate: f64, q_min: f64, iterations: ti.i32,
                    state_R: ti.types.ndarray(dtype=mat3d, ndim=1), state_P: ti.types.ndarray(dtype=mat3d, ndim=1),
                    diag: ti.types.ndarray(dtype=f64, ndim=2)):
        """EKF-SMT over batches b0..b1-1 in one launch (serial): random-walk prediction, iterated batched
        update, poses written to hist/hist64 (read back as the previous poses of later events)."""
        n = bearings.shape[0]
        ti.loop_config(serialize=True)
        for b in range(b0, b1):
            R = state_R[0]
            P = state_P[0]
            dt = mids[b] - mids[b - 1]
            q = ti.max(q_rate * dt, q_min)
            P += q * q * ti.Matrix.identity(f64, 3)
            p_inv = P.inverse()
            a = p_inv
            delta = vec3d(0, 0, 0)
            nv = 0.0
            ns = 0.0
            na = 0.0
            e_end = ti.min((b + 1) * batch_size, n)
            for it in range(iterations):
                rd = ti.cast(R, dtype)
                hh = mat3d(0)
                hr = vec3d(0, 0, 0)
                nv = 0.0
                ns = 0.0
                na = 0.0
                for e in range(b * batch_size, e_end):
                    k = prev_batch[e]
                    if k >= 0:
                        u0, v0 = project(hist[k] @ bearings[e], width, height, su, sv)
                        ok, r, S, H, pred, sup = measure(rd, bearings[e], u0, v0, pol[e], grad, cov, updates, width,
                                                         height, su, sv, contrast, sigma2, outlier2, min2)
                        if ok == 1:
                            nr = ti.abs(r) / ti.sqrt(S)
                            wt = ti.cast(1.0, dtype) / S
                            if nr > huber:
                                wt *= huber / nr
                            h64 = ti.cast(H, f64)
                            hh += ti.cast(wt, f64) * h64.outer_product(h64)
                            hr += ti.cast(wt * r, f64) * h64
                            nv += 1.0
                            if sup >= 0.5:
                                ns += 1.0
                                if pred * ti.cast(pol[e], dtype) > 0:
                                    na += 1.0
                if nv > 0:
                    a = p_inv + hh
                    step = a.inverse() @ (hr - p_inv @ delta)
                    delta += step
                    R = so3d.exp(step) @ R
            # re-orthonormalize (Gram-Schmidt on the columns)
            c0 = vec3d(R[0, 0], R[1, 0], R[2, 0]).normalized()
            c1 = vec3d(R[0, 1], R[1, 1], R[2, 1])
            c1 = (c1 - c0.dot(c1) * c0).normalized()
            c2 = c0.cross(c1)
            R = ti.Matrix.cols([c0, c1, c2])
            P = a.inverse()
            P = 0.5 * (P + P.transpose())
            state_R[0] = R
            state_P[0] = P
            hist64[b] = R
            hist[b] = ti.cast(R, dtype)
            diag[b - b0, 0] = nv
            diag[b - b0, 1] = ns
            diag[b - b0, 2] = na
            diag[b - b0, 3] = ti.max(P[0, 0], ti.max(P[1, 1], P[2, 2]))

    return k_project_prev, k_accumulate, k_loglik, k_ekf_track


def _tdt(np_dtype):
    return ti.f64 if np.dtype(np_dtype) == np.float64 else ti.f32


def _c(a, dtype):
    return np.ascontiguousarray(a, dtype=dtype)


def project_prev(poses, prev_idx, bearings, width: int, height: int, dtype=np.float32) -> np.ndarray:
    """Taichi twin of :func:`project_prev_numpy` (rows with prev_idx < 0 are 0, not NaN)."""
    ensure_init()
    k = _kernels(_tdt(dtype))[0]
    n = len(prev_idx)
    out = np.zeros((n, 2), dtype)
    if n:
        k(_c(np.asarray(poses).reshape(-1, 3, 3), dtype), _c(prev_idx, np.int32),
          _c(np.asarray(bearings).reshape(-1, 3), dtype), int(width), int(height), float(width / (2 * np.pi)),
          float(height / np.pi), out)
    return out


def ekf_accumulate(R, bearings, prev_uv, valid, pol, grad, cov, updates, contrast: float, sigma: float,
                   outlier_px: float, min_disp_px: float, huber: float) -> np.ndarray:
    """Huber-weighted normal equations of one pose over a batch; the dtype of ``grad`` selects f32/f64.

    Returns N_ACC float64 sums (see ACC): H^T W H upper triangle, H^T W r, counts of valid / supported
    (bilinear weight of mapped pixels >= 1/2) / polarity-agreeing supported measurements, sum of r^2/S over
    supported ones, sum of clipped squared normalized residuals, sums of p z_hat and z_hat^2 over supported ones.
    """
    ensure_init()
    dtype = grad.dtype
    k = _kernels(_tdt(dtype))[1]
    out = np.zeros(N_ACC, np.float64)
    h, w = updates.shape
    if len(pol):
        k(_c(np.asarray(R).reshape(1, 3, 3), dtype), _c(np.asarray(bearings).reshape(-1, 3), dtype),
          _c(prev_uv, dtype), _c(valid, np.int8), _c(pol, np.int8), grad, cov, updates, int(w), int(h),
          float(w / (2 * np.pi)), float(h / np.pi), float(contrast), float(sigma) ** 2, float(outlier_px) ** 2,
          float(min_disp_px) ** 2, float(huber), out)
    return out


def pf_loglik(particles, bearings, prev_uv, valid, pol, grad, cov, updates, contrast: float, sigma: float,
              outlier_px: float, min_disp_px: float, floor: float) -> np.ndarray:
    """(N,) float64 log-likelihood of a batch for each particle pose (N, 3, 3); dtype of ``grad`` selects f32/f64."""
    ensure_init()
    dtype = grad.dtype
    k = _kernels(_tdt(dtype))[2]
    parts = _c(np.asarray(particles).reshape(-1, 3, 3), dtype)
    out = np.zeros(len(parts), np.float64)
    h, w = updates.shape
    if len(pol):
        k(parts, _c(np.asarray(bearings).reshape(-1, 3), dtype), _c(prev_uv, dtype), _c(valid, np.int8),
          _c(pol, np.int8), grad, cov, updates, int(w), int(h), float(w / (2 * np.pi)), float(h / np.pi),
          float(contrast), float(sigma) ** 2, float(outlier_px) ** 2, float(min_disp_px) ** 2, float(floor),
          1.0 / _SQRT_2PI, out)
    return out


def ekf_track(hist, hist64, mids, b0: int, b1: int, batch_size: int, bearings, prev_batch, pol, grad, cov, updates,
              contrast: float, sigma: float, outlier_px: float, min_disp_px: float, huber: float, q_rate: float,
              q_min: float, iterations: int, state_R, state_P) -> np.ndarray:
    """EKF-SMT on batches b0..b1-1 in one launch (see module doc and ``ekf_track_numpy``).

    ``hist`` (nb, 3, 3) in the map dtype and ``hist64`` (float64) receive the poses; ``state_R`` / ``state_P``
    ((1, 3, 3) float64) carry the filter between calls. Returns (b1 - b0, 4) diagnostics per batch: valid,
    supported and polarity-agreeing measurements, largest diagonal entry of P (rad^2).
    """
    ensure_init()
    dtype = grad.dtype
    k = _kernels(_tdt(dtype))[3]
    diag = np.zeros((max(b1 - b0, 0), 4), np.float64)
    if b1 > b0:
        h, w = updates.shape
        k(hist, hist64, mids, int(b0), int(b1), int(batch_size), bearings, prev_batch, pol, grad, cov, updates,
          int(w), int(h), float(w / (2 * np.pi)), float(h / np.pi), float(contrast), float(sigma) ** 2,
          float(outlier_px) ** 2, float(min_disp_px) ** 2, float(huber), float(q_rate), float(q_min),
          int(iterations), state_R, state_P, diag)
    return diag


def ekf_track_numpy(hist, hist64, mids, b0, b1, batch_size, bearings, prev_batch, pol, grad, cov, updates, contrast,
                    sigma, outlier_px, min_disp_px, huber, q_rate, q_min, iterations, state_R, state_P):
    """float64 twin of :func:`ekf_track` (same in/out arrays)."""
    from ti_cmax import so3

    h, w = updates.shape
    n = len(pol)
    diag = np.zeros((max(b1 - b0, 0), 4))
    for b in range(b0, b1):
        R, P = state_R[0].copy(), state_P[0].copy()
        q = max(q_rate * (mids[b] - mids[b - 1]), q_min)
        P = P + q * q * np.eye(3)
        p_inv = np.linalg.inv(P)
        a, delta = p_inv, np.zeros(3)
        e0, e1 = b * batch_size, min((b + 1) * batch_size, n)
        pb = prev_batch[e0:e1]
        uv = np.nan_to_num(project_prev_numpy(hist, pb, bearings[e0:e1], w, h))
        acc = None
        for _ in range(iterations):
            acc = ekf_accumulate_numpy(R, bearings[e0:e1], uv, pb >= 0, pol[e0:e1], grad, cov, updates, contrast,
                                       sigma, outlier_px, min_disp_px, huber)
            if acc[9] > 0:
                hh = np.array([[acc[0], acc[1], acc[2]], [acc[1], acc[3], acc[4]], [acc[2], acc[4], acc[5]]])
                a = p_inv + hh
                step = np.linalg.solve(a, acc[6:9] - p_inv @ delta)
                delta = delta + step
                R = so3.exp(step) @ R
        u, _, vt = np.linalg.svd(R)
        R = u @ vt
        P = np.linalg.inv(a)
        P = 0.5 * (P + P.T)
        state_R[0], state_P[0] = R, P
        hist64[b] = R
        hist[b] = R
        diag[b - b0] = acc[9], acc[10], acc[11], np.max(np.diag(P))
    return diag


__all__ = ["ekf_track", "ekf_track_numpy", "ACC", "N_ACC", "project_prev", "project_prev_numpy", "ekf_accumulate",
           "ekf_accumulate_numpy", "pf_loglik", "pf_loglik_numpy"]
