"""SMT trackers' hot loops (paper Sec. II-A, App. B), Taichi + numpy twins.

Measurement (Eq. 1, linearized on the mapping EKFs' gradient map, same sign convention as kernels/mapping.py).
Each sensor pixel keeps a REFERENCE event: an earlier event of that pixel whose map point p_ref = p(R_ref b)
(under the pose estimated for its batch) is remembered. A new event k at the pixel, whose map point under the
pose being estimated is p = p(R b_k), measures the brightness change along the segment p_ref -> p:

    z = p_k n C,   z_hat = g(p_mid) . dp,   dp = p - p_ref (longitude wrapped),   p_mid = p_ref + dp / 2,

n being the number of events of the pixel since the reference (the current one included; all of one polarity).
Reference selection (:func:`select_references`, decided once per batch under a selection pose: the prediction):
the segment becomes a measurement once |dp| >= ``min_disp_px`` or n reaches ``max_events`` (> 0; and the event
becomes the new reference); shorter segments accumulate (n grows); a polarity change restarts the segment at the previous event (an
extremum of M lies between them: the linear model cannot describe it); |dp| > ``outlier_px`` or a reference
in the same batch (same pose: no displacement) restarts it at the current event without a measurement, and so
does a segment with an end beyond ``max_lat_deg`` of latitude: the equirectangular chart is singular at the poles
(u stretches by 1 / cos(lat)), where map-pixel segments, gradients and their linearization are meaningless. With
``min_disp_px`` below the map resolution this is the per-event model of [12] (previous event at the pixel).
Why a minimum segment of about one map pixel: the map holds pixel-averaged gradients; a shorter segment
samples the gradient below the map's resolution and, since events fire where the gradient is steep, its
increment is under-predicted (by 20-60 % below half a map pixel, measured at 1024 x 512 with ground-truth poses),
a motion-scale error that the tracker integrates into drift.

Why ``max_events``: the selection measures |dp| under the estimated motion; once the estimate says "at rest"
(after a stop or a turn back that it missed) no segment reaches the length, the events of the real motion only
add to n and nothing corrects the estimate. Two events of one polarity are a brightness change of 2 C, which
sub-pixel motion over a mapped gradient does not explain.

State references (:func:`ekf_track` with ``velocity_reference``, EKF-SMT's default): the reference point is
predicted from the state being estimated, p_ref = p(R exp(-w dt_ref) b), dt_ref the time from the reference's
batch to the event's (``ref_src``), instead of p(R_ref b) under the pose estimated for the reference's batch. A
fixed R_ref makes each measurement one of R relative to an earlier ESTIMATE taken as exact: the filter grows
overconfident (pose std 0.01 deg at 0.2 deg of error) and an error of the references passes into the pose and
back into later references (measured on simulated DAVIS240C sequences: 0.04 deg with ground-truth references,
lost at 1.3 s with its own by a runaway of 3 deg in 0.1 s, also on a ground-truth map). With the state's own
prediction the pose error is common to both ends (H_d only ties the pose to where on the map g is read) and the
increment measures the angular velocity (Eq. 38: h = -g . v dt). The constant-velocity extrapolation is off by
the velocity's random walk over dt_ref, whose variance q_acc^2 dt_ref^3 / 3 per axis is added to S (S += that x
|d z_hat / d theta_ref|^2), so old references weigh little. (Tried and dropped: the estimated relative motion
R_pred^T R_ref with only the velocity's deviation times dt_ref as its error: the references' pose jitter then
reads as velocity, lost within 0.2 s on every sequence.)

Constant angular acceleration (``state_a``, EKF-SMT's default): a segment dt_ref long measures the MEAN angular
velocity over it, which under an angular acceleration a is w - a dt_ref / 2, not the current w: a constant-velocity
state reads every segment as a velocity dt_ref / 2 old and, with its velocity random walk, trades that lag against
noise (measured on the simulated bicycle, seed 1: RMS velocity error 0.63 rad/s over 2.4-4 s, where |a| reaches
20 rad/s^2, 0.27 with the acceleration state; pipelines/baselines/smt.py). The state (R, w, a) predicts R exp(w dt +
a dt^2 / 2), w + a dt (a random walk of std q_jerk sqrt(dt)), reads the reference at p(R exp(-(w - a dt_ref / 2)
dt_ref) b), H_a = -(dt_ref / 2) H_w, and adds the jerk walk's extrapolation variance q_jerk^2 dt_ref^5 / 20 to S.
The update is 9-d. Its n x n algebra (n = 6, 9) runs in loops over a scratch array: unrolled 9 x 9 register
matrices took 7 minutes to compile.

g (and its 2x2 covariance P_g) is bilinearly interpolated at p_mid. Residual r = z - z_hat, variance
S = n sigma^2 + dp^T P_g dp + pos2 |g|^2 (n independent per-event errors; unmapped pixels keep the prior
covariance, so they weigh little by themselves). The last term (``position_var``, pos2): the two ends of a
segment are level crossings somewhere inside their map pixels (the map holds pixel averages and does not say
where within a pixel the level is crossed), each uniform over the pixel, variance 1/12 px^2 per axis-aligned
end, 2/12 for the two: the increment read off the gradient is uncertain by |g|^2 pos2, an error that grows with
the gradient. Without it S is the same for a steep and a flat gradient and the least squares fit of z on z_hat
(z nearly constant, n C with n = 1, 2; z_hat noisy through g) is attenuated: measured on a simulated
street sequence (seed 102) with a map built from ground-truth poses, at the ground-truth motion, the weighted
slope of z on z_hat was 0.73-0.85 after the gain calibration, and the tracker's speed was 6-15 % low.

Innovation consistency (``ekf_track`` diagnostics 5, 6, state references): at the prediction, y = H^T W r of a
batch has E[y y^T] = Lam P Lam + kappa Lam if the per-event errors are independent with the modelled variances
(kappa = 1) and kappa Lam if they are correlated or larger; with G the posterior covariance, kappa ~
(y^T G y - tr(G Lam P Lam)) / tr(G Lam), returned as numerator and denominator per batch (the pipeline sums
them: report ``innovation_kappa``).

Left perturbation R <- exp(d) R (world frame, as the back-end): d z_hat / d d = (X' x g_X)^T with X' = R b,
g_X = e_u du/dX' + e_v dv/dX' and e = d z_hat / d p = g(p_mid) + (1/2) (d g / d p_mid)^T dp (the bilinear map's
slope included: it is what ties the pose to the map rather than only to the previous poses).

* :func:`select_references` -- per batch, the reference (u, v, n) of each event and the per-pixel state update.
* :func:`ekf_accumulate` -- one pose: Huber-weighted normal equations H^T W H (6 values), H^T W r (3) and
  diagnostics, summed over a batch (serialized loop: reproducible).
* :func:`pf_loglik` -- many poses (particles): sum over the batch of log(N(r; 0, S) + floor) (parallel over
  particles, serial over events: reproducible).
* :func:`ekf_track` -- EKF-SMT over many batches in one launch (selection included). State: pose R (error d,
  R = exp(d) R_hat), camera-frame angular velocity w (error dw) and, with ``state_a``, angular acceleration a;
  6x6 (9x9) covariance. Prediction R <- R exp(w dt + a dt^2 / 2), w <- w + a dt, F = [[I, R dt, R dt^2 / 2],
  [0, I, I dt], [0, 0, I]], noise max(q_rate dt, q_min)^2 on d, q_acc^2 dt on w, q_jerk^2 dt on a. Pose
  references: the batch measures only the pose, so the iterated update x = P[:, d] (I + Lam P_dd)^-1 (b + Lam d_j)
  needs one 3x3 inverse (Lam = H^T W H, b = H^T W r of the batch). State references: H = (H_d, H_w[, H_a]) and
  the Gauss-Newton step of prior + batch (P^-1 + Lam) x = b + Lam x_j (SPD), posterior (P^-1 + Lam)^-1. One
  ti.func (``normal_equations``) sums the batch's Lam and b for the 3-, 6- and 9-d Jacobians.

Per-pixel state (``new_reference_state``): ref_b (batch of the reference's pose, -1: none), last_b and last_p
(batch and polarity of the pixel's last event), count (events since the reference). Every kernel has a float64
numpy twin (``*_numpy``). f32 uses the polynomial atan2 of kernels/pano.
"""

import functools
import types

import numpy as np

from ti_cmax.kernels import bilinear
from ti_cmax.kernels.bilinear import bilinear_funcs
from ti_cmax.kernels.pano import _proj_funcs, equirect_numpy
from ti_cmax.kernels.runtime import ensure_init, ti
from ti_cmax.kernels.so3 import so3_funcs as _so3_funcs

# slots of the ekf_accumulate output
ACC = ("h00", "h01", "h02", "h11", "h12", "h22", "b0", "b1", "b2",
       "valid", "supported", "agree", "nis", "chi2", "ppred", "count", "significant")
N_ACC = len(ACC)
_SQRT_2PI = float(np.sqrt(2.0 * np.pi))


def new_reference_state(num_pixels: int) -> dict:
    """Per-sensor-pixel reference memory (see module doc): no reference yet anywhere."""
    return {"ref_b": np.full(num_pixels, -1, np.int32), "last_b": np.full(num_pixels, -1, np.int32),
            "last_p": np.zeros(num_pixels, np.int8), "count": np.zeros(num_pixels, np.int32)}


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


def _v_band(height, max_lat_deg):
    """Largest |v - h/2| (map rows) of a map point within max_lat_deg of the equator."""
    return 0.5 * height * min(float(max_lat_deg), 90.0) / 90.0


def _wrap(du, width):
    return np.where(du > 0.5 * width, du - width, np.where(du <= -0.5 * width, du + width, du))


def select_references_numpy(hist, sel_R, b0, b1, batch_size, bearings, pix, pol, state, width, height,
                            outlier_px, min_disp_px, max_lat_deg, ref_uv, ref_n, ref_src=None, max_events=0):
    """Twin of :func:`select_references` (float64, event by event): fills ref_uv / ref_n of the events of batches
    b0..b1-1 (batch b's events start at b * batch_size; selection pose sel_R[b - b0]) and updates ``state``."""
    rb_, lb_, lp_, cn_ = state["ref_b"], state["last_b"], state["last_p"], state["count"]
    n = len(pol)
    for b in range(b0, b1):
        for e in range(b * batch_size, min((b + 1) * batch_size, n)):
            k, p = pix[e], int(pol[e])
            ref_n[e] = 0
            if rb_[k] < 0:
                rb_[k], cn_[k] = b, 0
            else:
                if p != lp_[k] and lb_[k] != rb_[k]:  # polarity change: restart at the previous event
                    rb_[k], cn_[k] = lb_[k], 0
                if rb_[k] == b:
                    cn_[k] += 1
                else:
                    x0 = np.asarray(hist[rb_[k]], np.float64) @ np.asarray(bearings[e], np.float64)
                    x1 = np.asarray(sel_R[b - b0], np.float64) @ np.asarray(bearings[e], np.float64)
                    (u0, u1), (v0, v1) = equirect_numpy(np.stack([x0, x1]), width, height)
                    du, dv = float(_wrap(u1 - u0, width)), v1 - v0
                    d2 = du * du + dv * dv
                    band = _v_band(height, max_lat_deg)
                    if d2 > outlier_px ** 2 or abs(v0 - 0.5 * height) > band or abs(v1 - 0.5 * height) > band:
                        rb_[k], cn_[k] = b, 0
                    elif d2 >= min_disp_px ** 2 or 0 < max_events <= cn_[k] + 1:
                        ref_uv[e] = u0, v0
                        ref_n[e] = cn_[k] + 1
                        if ref_src is not None:
                            ref_src[e] = rb_[k]
                        rb_[k], cn_[k] = b, 0
                    else:
                        cn_[k] += 1
            lb_[k], lp_[k] = b, p


def _measure_numpy(R, bearings, ref_uv, ref_n, pol, grad, cov, updates, contrast, sigma2, parts=False, pos2=0.0):
    """Per-event (ok, r, S, H (n, 3), pred, support) for one pose R (float64); ``parts``: also (g_u, g_v, e_u, e_v)."""
    h, w = updates.shape
    xw = np.asarray(bearings, np.float64) @ np.asarray(R, np.float64).T
    u, v = equirect_numpy(xw, w, h)
    du = _wrap(u - ref_uv[:, 0], w)
    dv = v - ref_uv[:, 1]
    cnt = np.asarray(ref_n, np.float64)
    ok = cnt > 0
    mu = ref_uv[:, 0] + 0.5 * du
    mv = ref_uv[:, 1] + 0.5 * dv
    # g, P and the mapped weight bilinear at (mu, mv) (longitude wrapped, rows outside the map contribute nothing)
    g, gdu, gdv = bilinear.sample_numpy(grad, mu, mv, wrap_u=True)
    P = bilinear.sample_numpy(cov, mu, mv, wrap_u=True)[0]
    sup = bilinear.sample_numpy(updates > 0, mu, mv, wrap_u=True)[0]
    pred = g[:, 0] * du + g[:, 1] * dv
    S = sigma2 * np.maximum(cnt, 1.0) + du * du * P[:, 0] + 2 * du * dv * P[:, 1] + dv * dv * P[:, 2] \
        + pos2 * (g[:, 0] ** 2 + g[:, 1] ** 2)
    r = np.asarray(pol, np.float64) * cnt * contrast - pred
    jdu, jdv = _project_jacobian_numpy(xw, w, h)
    # d z_hat / d p = g(p_mid) + (1/2) (d g / d p_mid)^T dp  (p_mid moves by half of p)
    eu = g[:, 0] + 0.5 * (du * gdu[:, 0] + dv * gdu[:, 1])
    ev = g[:, 1] + 0.5 * (du * gdv[:, 0] + dv * gdv[:, 1])
    gx = eu[:, None] * jdu + ev[:, None] * jdv
    H = np.cross(xw, gx)
    if parts:
        return ok, r, S, H, pred, sup, (g[:, 0], g[:, 1], eu, ev)
    return ok, r, S, H, pred, sup


def _measure_cv_numpy(R, w, dtr, bearings, ref_n, pol, grad, cov, updates, contrast, sigma2, q2=0.0, a=None,
                      q5=0.0, pos2=0.0):
    """State-referenced twin (float64): per event (ok, r, S, H_d (n, 3) world, H_w (n, 3) camera, pred, support)
    with the reference point p(R exp(-(w - a dt_ref / 2) dt_ref) b); ``dtr`` (n,) the reference's age, ``a`` the
    angular acceleration (None: 0; H_a = -(dt_ref / 2) H_w)."""
    from ti_cmax import so3

    h, wd = updates.shape
    R = np.asarray(R, np.float64)
    b = np.asarray(bearings, np.float64)
    dtr = np.asarray(dtr, np.float64)
    w = np.asarray(w, np.float64)[None] - (0.0 if a is None else 0.5 * dtr[:, None] * np.asarray(a, np.float64))
    R_ref = R @ so3.exp(-dtr[:, None] * w)  # (n, 3, 3)
    xr = np.einsum("nij,nj->ni", R_ref, b)
    u0, v0 = equirect_numpy(xr, wd, h)
    ok, r, S, H, pred, sup, (gu, gv, eu, ev) = _measure_numpy(R, b, np.stack([u0, v0], 1), ref_n, pol, grad, cov,
                                                              updates, contrast, sigma2, parts=True, pos2=pos2)
    jru, jrv = _project_jacobian_numpy(xr, wd, h)
    hr = np.cross(xr, (eu - 2 * gu)[:, None] * jru + (ev - 2 * gv)[:, None] * jrv)
    jr = so3.right_jacobian(-dtr[:, None] * w).reshape(-1, 3, 3)
    Hw = -dtr[:, None] * np.einsum("nji,nj->ni", jr, np.einsum("nji,nj->ni", R_ref, hr))
    S = S + (q2 * dtr ** 3 + q5 * dtr ** 5) * np.sum(hr * hr, 1)
    return ok, r, S, H + hr, Hw, pred, sup


def ekf_accumulate_numpy(R, bearings, ref_uv, ref_n, pol, grad, cov, updates, contrast, sigma, huber,
                         position_var=0.0):
    """Twin of :func:`ekf_accumulate` (float64): returns the N_ACC sums."""
    ok, r, S, H, pred, sup = _measure_numpy(R, bearings, ref_uv, ref_n, pol, grad, cov, updates, contrast,
                                            sigma * sigma, pos2=position_var)
    out = np.zeros(N_ACC)
    nr = np.abs(r) / np.sqrt(S)
    wt = np.where(nr <= huber, 1.0, huber / np.maximum(nr, 1e-300)) / S
    wt = np.where(ok, wt, 0.0)
    hw = H * wt[:, None]
    hh = hw.T @ H
    out[0:6] = hh[0, 0], hh[0, 1], hh[0, 2], hh[1, 1], hh[1, 2], hh[2, 2]
    out[6:9] = hw.T @ r
    supported = ok & (sup >= 0.5)
    pp = pred * np.asarray(pol, np.float64)
    out[9] = ok.sum()
    out[10] = supported.sum()
    significant = supported & (pp * pp > S)  # |z_hat| above its std: its sign means something
    out[11] = (significant & (pp > 0)).sum()
    out[16] = significant.sum()
    out[12] = np.sum(np.where(supported, r * r / S, 0.0))
    out[13] = np.sum(np.where(ok, np.minimum(nr, huber) ** 2, 0.0))
    out[14] = np.sum(np.where(supported, pp, 0.0))
    out[15] = np.sum(np.where(supported, np.asarray(ref_n, np.float64), 0.0))
    return out


def pf_loglik_numpy(particles, bearings, ref_uv, ref_n, pol, grad, cov, updates, contrast, sigma, floor,
                    position_var=0.0):
    """Twin of :func:`pf_loglik`: (N,) sum over events of log(N(r; 0, S) + floor) per particle (float64)."""
    out = np.zeros(len(particles))
    for i, R in enumerate(np.asarray(particles, np.float64)):
        ok, r, S, _, _, _ = _measure_numpy(R, bearings, ref_uv, ref_n, pol, grad, cov, updates, contrast,
                                           sigma * sigma, pos2=position_var)
        dens = np.exp(-0.5 * r * r / S) / (_SQRT_2PI * np.sqrt(S))
        out[i] = np.sum(np.where(ok, np.log(dens + floor), 0.0))
    return out


# ----------------------------------------------------------------------------------------------------------------
# Taichi kernels
# ----------------------------------------------------------------------------------------------------------------
def _event_types(dtype):
    """Taichi types of the event kernels' arguments: bearing, rotation (map dtype) and index."""
    return ti.types.vector(3, dtype), ti.types.matrix(3, 3, dtype), ti.i32


@functools.cache
def _selection_funcs(dtype):
    """ti.funcs of the reference selection in the map dtype: longitude wrap and one event's reference."""
    project = _proj_funcs(dtype)[0]
    i32 = ti.i32

    @ti.func
    def wrap(du, width):
        wf = ti.cast(width, dtype)
        if du > ti.cast(0.5, dtype) * wf:
            du -= wf
        elif du <= -ti.cast(0.5, dtype) * wf:
            du += wf
        return du

    @ti.func
    def select_event(e, b, R_sel, hist: ti.template(), bearings: ti.template(), pix: ti.template(),
                     pol: ti.template(), ref_b: ti.template(), last_b: ti.template(), last_p: ti.template(),
                     count: ti.template(), width, height, su, sv, outlier2, min2, v_band, max_n, ref_uv: ti.template(),
                     ref_n: ti.template(), ref_src: ti.template()):
        """Reference of event e (batch b) under the selection pose R_sel; updates the pixel's state."""
        k = pix[e]
        p = ti.cast(pol[e], i32)
        ref_n[e] = 0
        if ref_b[k] < 0:
            ref_b[k] = b
            count[k] = 0
        else:
            if p != ti.cast(last_p[k], i32) and last_b[k] != ref_b[k]:
                ref_b[k] = last_b[k]
                count[k] = 0
            if ref_b[k] == b:
                count[k] += 1
            else:
                u0, v0 = project(hist[ref_b[k]] @ bearings[e], width, height, su, sv)
                u1, v1 = project(R_sel @ bearings[e], width, height, su, sv)
                du = wrap(u1 - u0, width)
                dv = v1 - v0
                d2 = du * du + dv * dv
                half_h = ti.cast(0.5 * height, dtype)
                if d2 > outlier2 or ti.abs(v0 - half_h) > v_band or ti.abs(v1 - half_h) > v_band:
                    ref_b[k] = b
                    count[k] = 0
                elif d2 >= min2 or (max_n > 0 and count[k] + 1 >= max_n):
                    ref_uv[e, 0] = u0
                    ref_uv[e, 1] = v0
                    ref_n[e] = count[k] + 1
                    ref_src[e] = ref_b[k]
                    ref_b[k] = b
                    count[k] = 0
                else:
                    count[k] += 1
        last_b[k] = b
        last_p[k] = pol[e]

    return types.SimpleNamespace(wrap=wrap, select_event=select_event)


@functools.cache
def _event_funcs(dtype):
    """ti.funcs of one event in the map dtype: reference selection, the segment's increment model, its Jacobians
    (fixed or state references) and the Huber weight."""
    project, project_jacobian = _proj_funcs(dtype)
    bl = bilinear_funcs(dtype)
    so3t = _so3_funcs(dtype)
    sel = _selection_funcs(dtype)
    wrap, select_event = sel.wrap, sel.select_event

    @ti.func
    def weigh(r, S, agree, sup, huber):
        """Huber weight of a measurement and its diagnostic counts (supported, significant, agreeing) as f64."""
        nr = ti.abs(r) / ti.sqrt(S)
        wt = ti.cast(1.0, dtype) / S
        if nr > huber:
            wt *= huber / nr
        supported = sup >= ti.cast(0.5, dtype)
        significant = supported and agree * agree > S
        return (ti.cast(wt, ti.f64), ti.cast(supported, ti.f64), ti.cast(significant, ti.f64),
                ti.cast(significant and agree > 0, ti.f64))

    @ti.func
    def segment(x, u0, v0, cnt, pol, grad: ti.template(), cov: ti.template(), updates: ti.template(), width, height,
                su, sv, contrast, sigma2, pos2):
        """Increment model of the segment p_ref = (u0, v0) -> p(x) (module doc): r, S, p z_hat, support, and
        e = d z_hat / d p (end point) as (eu, ev); d z_hat / d p_ref = e - 2 g."""
        pu, pv = project(x, width, height, su, sv)
        du = wrap(pu - u0, width)
        dv = pv - v0
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
        nf = ti.cast(cnt, dtype)
        S = sigma2 * nf + du * du * p00 + ti.cast(2.0, dtype) * du * dv * p01 + dv * dv * p11 + pos2 * (gu * gu + gv * gv)
        z = ti.cast(pol, dtype) * nf * contrast
        r = z - pred
        eu = gu + ti.cast(0.5, dtype) * (du * gu_u + dv * gv_u)
        ev = gv + ti.cast(0.5, dtype) * (du * gu_v + dv * gv_v)
        return r, S, pred * ti.cast(pol, dtype), sup, eu, ev, gu, gv

    @ti.func
    def measure(R, b, u0, v0, cnt, pol, grad: ti.template(), cov: ti.template(), updates: ti.template(),
                width, height, su, sv, contrast, sigma2, pos2):
        """(r, S, H, p z_hat, support) of one event with a fixed reference (u0, v0) n = cnt events back."""
        x = R @ b
        r, S, agree, sup, eu, ev, _, _ = segment(x, u0, v0, cnt, pol, grad, cov, updates, width, height, su, sv,
                                                 contrast, sigma2, pos2)
        jdu, jdv = project_jacobian(x, su, sv)
        H = x.cross(eu * jdu + ev * jdv)
        return r, S, H, agree, sup

    @ti.func
    def measure_cv(R, w, dtr, b, cnt, pol, grad: ti.template(), cov: ti.template(), updates: ti.template(),
                   width, height, su, sv, contrast, sigma2, pos2, q2, q5):
        """State-referenced measurement (module doc): the reference point is p(R exp(-w dtr) b), w the mean angular
        velocity over the segment (w - a dtr / 2 with an acceleration state), so the segment depends on the state,
        not on an earlier estimate. (r, S, H_d (world), H_w (camera; H_a = -(dtr / 2) H_w), p z_hat, support)."""
        x = R @ b
        R_ref = R @ so3t.exp(-w * dtr)
        xr = R_ref @ b
        u0, v0 = project(xr, width, height, su, sv)
        r, S, agree, sup, eu, ev, gu, gv = segment(x, u0, v0, cnt, pol, grad, cov, updates, width, height, su, sv,
                                                   contrast, sigma2, pos2)
        jdu, jdv = project_jacobian(x, su, sv)
        jru, jrv = project_jacobian(xr, su, sv)
        two = ti.cast(2.0, dtype)
        hr = xr.cross((eu - two * gu) * jru + (ev - two * gv) * jrv)
        Hd = x.cross(eu * jdu + ev * jdv) + hr
        Hw = -dtr * (so3t.jr(-w * dtr).transpose() @ (R_ref.transpose() @ hr))
        # the extrapolated reference is off by the random walks over dt_ref: variance q2 dt_ref^3 + q5 dt_ref^5
        # per axis of the reference's rotation (q2 = q_acc^2 / 3 from w's, q5 = q_jerk^2 / 20 from a's)
        dt3 = dtr * dtr * dtr
        S += (q2 + q5 * dtr * dtr) * dt3 * hr.dot(hr)
        return r, S, Hd, Hw, agree, sup

    return types.SimpleNamespace(select_event=select_event, weigh=weigh, measure=measure, measure_cv=measure_cv)


@functools.cache
def _select_kernel(dtype):
    select_event = _event_funcs(dtype).select_event
    vec3, mat3, i32 = _event_types(dtype)

    @ti.kernel
    def k_select(hist: ti.types.ndarray(dtype=mat3, ndim=1), sel_R: ti.types.ndarray(dtype=mat3, ndim=1),
                 b0: i32, b1: i32, batch_size: i32, bearings: ti.types.ndarray(dtype=vec3, ndim=1),
                 pix: ti.types.ndarray(dtype=i32, ndim=1), pol: ti.types.ndarray(dtype=ti.i8, ndim=1),
                 ref_b: ti.types.ndarray(dtype=i32, ndim=1), last_b: ti.types.ndarray(dtype=i32, ndim=1),
                 last_p: ti.types.ndarray(dtype=ti.i8, ndim=1), count: ti.types.ndarray(dtype=i32, ndim=1),
                 width: i32, height: i32, su: dtype, sv: dtype, outlier2: dtype, min2: dtype, v_band: dtype,
                 max_n: i32, ref_uv: ti.types.ndarray(dtype=dtype, ndim=2), ref_n: ti.types.ndarray(dtype=i32, ndim=1),
                 ref_src: ti.types.ndarray(dtype=i32, ndim=1)):
        n = bearings.shape[0]
        ti.loop_config(serialize=True)
        for b in range(b0, b1):
            for e in range(b * batch_size, ti.min((b + 1) * batch_size, n)):
                select_event(e, b, sel_R[b - b0], hist, bearings, pix, pol, ref_b, last_b, last_p, count, width,
                             height, su, sv, outlier2, min2, v_band, max_n, ref_uv, ref_n, ref_src)

    return k_select


@functools.cache
def _batch_kernels(dtype):
    """k_accumulate (one pose: the EKF's normal equations) and k_loglik (many poses: the PF's likelihoods)."""
    measure = _event_funcs(dtype).measure
    vec3, mat3, i32 = _event_types(dtype)

    @ti.kernel
    def k_accumulate(R: ti.types.ndarray(dtype=mat3, ndim=1), bearings: ti.types.ndarray(dtype=vec3, ndim=1),
                     ref_uv: ti.types.ndarray(dtype=dtype, ndim=2), ref_n: ti.types.ndarray(dtype=i32, ndim=1),
                     pol: ti.types.ndarray(dtype=ti.i8, ndim=1), grad: ti.types.ndarray(dtype=dtype, ndim=3),
                     cov: ti.types.ndarray(dtype=dtype, ndim=3), updates: ti.types.ndarray(dtype=i32, ndim=2),
                     width: i32, height: i32, su: dtype, sv: dtype, contrast: dtype, sigma2: dtype, pos2: dtype,
                     huber: dtype, out: ti.types.ndarray(dtype=ti.f64, ndim=1)):
        rot = R[0]
        ti.loop_config(serialize=True)
        for e in range(bearings.shape[0]):
            if ref_n[e] > 0:
                r, S, H, agree, sup = measure(rot, bearings[e], ref_uv[e, 0], ref_uv[e, 1], ref_n[e], pol[e], grad,
                                              cov, updates, width, height, su, sv, contrast, sigma2, pos2)
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
                    out[14] += ti.cast(agree, ti.f64)
                    out[15] += ti.cast(ref_n[e], ti.f64)
                    if agree * agree > S:
                        out[16] += 1.0
                        if agree > 0:
                            out[11] += 1.0


    @ti.kernel
    def k_loglik(particles: ti.types.ndarray(dtype=mat3, ndim=1), bearings: ti.types.ndarray(dtype=vec3, ndim=1),
                 ref_uv: ti.types.ndarray(dtype=dtype, ndim=2), ref_n: ti.types.ndarray(dtype=i32, ndim=1),
                 pol: ti.types.ndarray(dtype=ti.i8, ndim=1), grad: ti.types.ndarray(dtype=dtype, ndim=3),
                 cov: ti.types.ndarray(dtype=dtype, ndim=3), updates: ti.types.ndarray(dtype=i32, ndim=2),
                 width: i32, height: i32, su: dtype, sv: dtype, contrast: dtype, sigma2: dtype, pos2: dtype,
                 floor: dtype, inv_sqrt_2pi: dtype, out: ti.types.ndarray(dtype=ti.f64, ndim=1)):
        ti.loop_config(block_dim=4)  # few, heavy iterations: spread them over the threads
        for i in range(particles.shape[0]):
            rot = particles[i]
            acc = ti.cast(0.0, ti.f64)
            for e in range(bearings.shape[0]):
                if ref_n[e] > 0:
                    r, S, H, agree, sup = measure(rot, bearings[e], ref_uv[e, 0], ref_uv[e, 1], ref_n[e], pol[e],
                                                  grad, cov, updates, width, height, su, sv, contrast, sigma2, pos2)
                    dens = ti.exp(-ti.cast(0.5, dtype) * r * r / S) * inv_sqrt_2pi / ti.sqrt(S)
                    acc += ti.cast(ti.log(dens + floor), ti.f64)
            out[i] = acc

    return k_accumulate, k_loglik


@functools.cache
def _filter_funcs():
    """The filter's float64 algebra: SO(3) functions and the n x n products and inverse over a scratch array."""
    f64 = ti.f64
    so3d = _so3_funcs(f64)

    # the filter's n x n algebra (n = 6 or 9) runs in loops over a scratch array ``work`` (k, 9, 9): unrolled
    # register matrices of that size took minutes to compile (7 min measured for n = 9)
    @ti.func
    def ws_matmul(work: ti.template(), a, b, c, n, transpose_b):
        """work[c] = work[a] @ work[b] (or @ work[b]^T)."""
        for i, j in ti.ndrange(n, n):
            s = ti.cast(0.0, f64)
            for k in range(n):
                s += work[a, i, k] * (work[b, j, k] if transpose_b else work[b, k, j])
            work[c, i, j] = s

    @ti.func
    def ws_inv_spd(work: ti.template(), src, dst, tmp, n):
        """work[dst] = inverse of the symmetric positive definite work[src] (Gauss-Jordan, no pivoting needed),
        symmetrized; work[tmp] is overwritten."""
        for i, j in ti.ndrange(n, n):
            work[tmp, i, j] = work[src, i, j]
            work[dst, i, j] = ti.cast(1.0 if i == j else 0.0, f64)
        for k in range(n):
            piv = 1.0 / work[tmp, k, k]
            for j in range(n):
                work[tmp, k, j] *= piv
                work[dst, k, j] *= piv
            for i in range(n):
                if i != k:
                    f = work[tmp, i, k]
                    for j in range(n):
                        work[tmp, i, j] -= f * work[tmp, k, j]
                        work[dst, i, j] -= f * work[dst, k, j]
        for i, j in ti.ndrange(n, n):
            if i < j:
                s = 0.5 * (work[dst, i, j] + work[dst, j, i])
                work[dst, i, j] = s
                work[dst, j, i] = s

    return types.SimpleNamespace(so3d=so3d, ws_matmul=ws_matmul, ws_inv_spd=ws_inv_spd)


@functools.cache
def _normal_equations(dtype):
    ef = _event_funcs(dtype)
    weigh, measure, measure_cv = ef.weigh, ef.measure, ef.measure_cv
    f64 = ti.f64

    @ti.func
    def normal_equations(m: ti.template(), rd, wd, ad, b, e0, e_end, mids: ti.template(), bearings: ti.template(),
                         ref_uv: ti.template(), ref_n: ti.template(), ref_src: ti.template(), pol: ti.template(),
                         grad: ti.template(), cov: ti.template(), updates: ti.template(), width, height, su, sv,
                         contrast, sigma2, pos2, q2, q5, huber):
        """Huber-weighted normal equations Lam = H^T W H (m x m), H^T W r (m) of the events e0..e_end-1 of batch b
        and their counts (valid, supported, agreeing, significant), float64. m = 3: references fixed in ref_uv,
        H = H_d; m = 6: state references, H = (H_d, H_w); m = 9: also the acceleration, H_a = -(dt_ref / 2) H_w."""
        lam = ti.Matrix.zero(f64, m, m)
        hb = ti.Vector.zero(f64, m)
        cnt = ti.Vector.zero(f64, 4)
        for e in range(e0, e_end):
            if ref_n[e] > 0:
                h = ti.Vector.zero(f64, m)
                r = ti.cast(0.0, dtype)
                S = ti.cast(1.0, dtype)
                agree = ti.cast(0.0, dtype)
                sup = ti.cast(0.0, dtype)
                if ti.static(m == 3):
                    r, S, H, agree, sup = measure(rd, bearings[e], ref_uv[e, 0], ref_uv[e, 1], ref_n[e], pol[e], grad,
                                                  cov, updates, width, height, su, sv, contrast, sigma2, pos2)
                    for i in ti.static(range(3)):
                        h[i] = ti.cast(H[i], f64)
                else:
                    dtr = ti.cast(mids[b] - mids[ref_src[e]], dtype)
                    r, S, Hd, Hw, agree, sup = measure_cv(rd, wd - ti.cast(0.5, dtype) * dtr * ad, dtr, bearings[e],
                                                          ref_n[e], pol[e], grad, cov, updates, width, height, su, sv,
                                                          contrast, sigma2, pos2, q2, q5)
                    for i in ti.static(range(3)):
                        h[i] = ti.cast(Hd[i], f64)
                        h[i + 3] = ti.cast(Hw[i], f64)
                        if ti.static(m == 9):
                            h[i + 6] = -0.5 * ti.cast(dtr, f64) * ti.cast(Hw[i], f64)
                wt, cs, cg, ca = weigh(r, S, agree, sup, huber)
                lam += wt * h.outer_product(h)
                hb += wt * ti.cast(r, f64) * h
                cnt += ti.Vector([1.0, cs, ca, cg], f64)
        return lam, hb, cnt

    return normal_equations


@functools.cache
def _track_kernel(dtype):
    """k_ekf_track in the map dtype ``dtype``; the filter's state and algebra are float64."""
    select_event = _selection_funcs(dtype).select_event
    normal_equations = _normal_equations(dtype)
    ff = _filter_funcs()
    ws_matmul, ws_inv_spd, so3d = ff.ws_matmul, ff.ws_inv_spd, ff.so3d
    vec3, mat3, i32 = _event_types(dtype)
    f64 = ti.f64
    mat3d = ti.types.matrix(3, 3, f64)
    vec3d = ti.types.vector(3, f64)

    @ti.kernel
    def k_ekf_track(hist: ti.types.ndarray(dtype=mat3, ndim=1), hist64: ti.types.ndarray(dtype=mat3d, ndim=1),
                    mids: ti.types.ndarray(dtype=f64, ndim=1), b0: ti.i32, b1: ti.i32, batch_size: ti.i32,
                    bearings: ti.types.ndarray(dtype=vec3, ndim=1), pix: ti.types.ndarray(dtype=i32, ndim=1),
                    pol: ti.types.ndarray(dtype=ti.i8, ndim=1), ref_b: ti.types.ndarray(dtype=i32, ndim=1),
                    last_b: ti.types.ndarray(dtype=i32, ndim=1), last_p: ti.types.ndarray(dtype=ti.i8, ndim=1),
                    count: ti.types.ndarray(dtype=i32, ndim=1), ref_uv: ti.types.ndarray(dtype=dtype, ndim=2),
                    ref_n: ti.types.ndarray(dtype=i32, ndim=1), ref_src: ti.types.ndarray(dtype=i32, ndim=1),
                    grad: ti.types.ndarray(dtype=dtype, ndim=3),
                    cov: ti.types.ndarray(dtype=dtype, ndim=3), updates: ti.types.ndarray(dtype=ti.i32, ndim=2),
                    width: ti.i32, height: ti.i32, su: dtype, sv: dtype, contrast: dtype, sigma2: dtype, pos2: dtype,
                    outlier2: dtype, min2: dtype, v_band: dtype, max_n: ti.i32, huber: dtype, q_rate: f64, q_min: f64,
                    q_acc: f64, q_jerk: f64, iterations: ti.i32, cv_meas: ti.i32,
                    state_R: ti.types.ndarray(dtype=mat3d, ndim=1), state_w: ti.types.ndarray(dtype=vec3d, ndim=1),
                    state_a: ti.types.ndarray(dtype=vec3d, ndim=1), state_P: ti.types.ndarray(dtype=f64, ndim=3),
                    work: ti.types.ndarray(dtype=f64, ndim=3), diag: ti.types.ndarray(dtype=f64, ndim=2),
                    ns: ti.template()):
        """EKF-SMT over batches b0..b1-1 in one launch (serial): constant-velocity (ns = 6) or constant-acceleration
        (ns = 9) prediction, iterated batched update, poses written to hist/hist64 (read back as the previous poses
        of later events). work[0]: P, [1]: F, then the matrix to invert, [2]: F P, [3]: P^-1, [4]: posterior,
        [5], [6]: scratch."""
        n = bearings.shape[0]
        eye = ti.Matrix.identity(f64, 3)
        ti.loop_config(serialize=True)
        for b in range(b0, b1):
            dt = mids[b] - mids[b - 1]
            # prediction: R <- R exp(w dt + a dt^2 / 2), w <- w + a dt (camera frame); F maps the error state
            # (d world-frame pose, dw, da) through it
            w = state_w[0]
            a = state_a[0]
            phi = w * dt
            if ti.static(ns == 9):
                phi += 0.5 * dt * dt * a
            R_pred = state_R[0] @ so3d.exp(phi)
            for i, j in ti.ndrange(ns, ns):
                work[0, i, j] = state_P[0, i, j]
                work[1, i, j] = ti.cast(1.0 if i == j else 0.0, f64)
            for i, j in ti.static(ti.ndrange(3, 3)):
                work[1, i, j + 3] = R_pred[i, j] * dt
                if ti.static(ns == 9):
                    work[1, i, j + 6] = 0.5 * dt * dt * R_pred[i, j]
            if ti.static(ns == 9):
                for i in ti.static(range(3)):
                    work[1, i + 3, i + 6] = dt
                w += a * dt
            ws_matmul(work, 1, 0, 2, ns, False)
            ws_matmul(work, 2, 1, 0, ns, True)
            q = ti.max(q_rate * dt, q_min)
            for i in ti.static(range(3)):
                work[0, i, i] += q * q
                work[0, i + 3, i + 3] += q_acc * q_acc * dt
                if ti.static(ns == 9):
                    work[0, i + 6, i + 6] += q_jerk * q_jerk * dt
            for i, j in ti.ndrange(ns, ns):
                work[4, i, j] = work[0, i, j]  # the posterior when nothing is measured
            w_pred = w
            R = R_pred
            e0 = b * batch_size
            e_end = ti.min((b + 1) * batch_size, n)
            rp = ti.cast(R_pred, dtype)
            for e in range(e0, e_end):  # references, selected under the prediction
                select_event(e, b, rp, hist, bearings, pix, pol, ref_b, last_b, last_p, count, width, height, su,
                             sv, outlier2, min2, v_band, max_n, ref_uv, ref_n, ref_src)
            # the extrapolation error of a state reference dt_ref back: variance (q_acc^2 / 3) dt_ref^3 per axis
            # from w's random walk, (q_jerk^2 / 20) dt_ref^5 from a's (constant acceleration)
            q2 = ti.cast(q_acc * q_acc / 3.0, dtype)
            q5 = ti.cast(q_jerk * q_jerk / 20.0, dtype)
            cnt = ti.Vector.zero(f64, 4)
            kap_num = ti.cast(0.0, f64)
            kap_den = ti.cast(0.0, f64)
            if cv_meas:
                # state-referenced measurements: Gauss-Newton on prior + batch in the ns-d error state,
                # (P^-1 + Lam) x = b + Lam x_j; the posterior covariance is (P^-1 + Lam)^-1
                ws_inv_spd(work, 0, 3, 5, ns)
                x = ti.Vector.zero(f64, ns)
                for it in range(iterations):
                    lam, hb, cnt_it = normal_equations(ns, ti.cast(R, dtype), ti.cast(w, dtype), ti.cast(a, dtype), b,
                                                       e0, e_end, mids, bearings, ref_uv, ref_n, ref_src, pol, grad,
                                                       cov, updates, width, height, su, sv, contrast, sigma2, pos2, q2, q5,
                                                       huber)
                    cnt = cnt_it
                    if it == 0:  # the batch's information, kept for the consistency statistic
                        for i in ti.static(range(ns)):
                            for j in ti.static(range(ns)):
                                work[6, i, j] = lam[i, j]
                    if cnt[0] > 0:
                        for i in ti.static(range(ns)):  # (nested: a static loop of ns^2 would warn)
                            for j in ti.static(range(ns)):
                                work[1, i, j] = work[3, i, j] + lam[i, j]
                        ws_inv_spd(work, 1, 4, 5, ns)
                        if it == 0:
                            # innovation consistency (module doc): y = H^T W r at the prediction has E[y y^T] =
                            # Lam P Lam + kappa Lam; with G = the posterior, kappa ~ (y^T G y - tr(G Lam P Lam)) /
                            # tr(G Lam)
                            ws_matmul(work, 6, 0, 7, ns, False)  # Lam P
                            ws_matmul(work, 7, 6, 2, ns, False)  # Lam P Lam
                            ygy = ti.cast(0.0, f64)
                            for i in ti.static(range(ns)):
                                for j in ti.static(range(ns)):
                                    ygy += hb[i] * work[4, i, j] * hb[j]
                            t1 = ti.cast(0.0, f64)
                            t2 = ti.cast(0.0, f64)
                            for i, j in ti.ndrange(ns, ns):
                                t1 += work[4, i, j] * work[2, j, i]
                                t2 += work[4, i, j] * work[6, j, i]
                            kap_num = ygy - t1
                            kap_den = t2
                    if cnt[0] > 0:
                        rhs = hb + lam @ x
                        for i in ti.static(range(ns)):
                            s = ti.cast(0.0, f64)
                            for j in ti.static(range(ns)):
                                s += work[4, i, j] * rhs[j]
                            x[i] = s
                        R = so3d.exp(vec3d(x[0], x[1], x[2])) @ R_pred
                        w = w_pred + vec3d(x[3], x[4], x[5])
                        if ti.static(ns == 9):
                            a = state_a[0] + vec3d(x[6], x[7], x[8])
            else:
                # measurements of the pose only (fixed references): x = P[:, d] (I + Lam P_dd)^-1 (b + Lam d),
                # posterior P - P[:, d] (I + Lam P_dd)^-1 Lam P[d, :]
                pdd = mat3d(0)
                for i, j in ti.static(ti.ndrange(3, 3)):
                    pdd[i, j] = work[0, i, j]
                d = vec3d(0, 0, 0)
                for it in range(iterations):
                    lam, hb, cnt_it = normal_equations(3, ti.cast(R, dtype), ti.cast(w, dtype), ti.cast(a, dtype), b,
                                                       e0, e_end, mids, bearings, ref_uv, ref_n, ref_src, pol, grad,
                                                       cov, updates, width, height, su, sv, contrast, sigma2, pos2, q2, q5,
                                                       huber)
                    cnt = cnt_it
                    if cnt[0] > 0:
                        m = (eye + lam @ pdd).inverse()
                        v = m @ (hb + lam @ d)
                        ml = m @ lam
                        for i in range(ns):  # x = P[:, d] v; work[5] = P[:, d] (I + Lam P_dd)^-1 Lam
                            xi = ti.cast(0.0, f64)
                            for k in ti.static(range(3)):
                                xi += work[0, i, k] * v[k]
                            if i < 3:
                                d[i] = xi
                            elif i < 6:
                                w[i - 3] = w_pred[i - 3] + xi
                            for j in ti.static(range(3)):
                                s = ti.cast(0.0, f64)
                                for k in ti.static(range(3)):
                                    s += work[0, i, k] * ml[k, j]
                                work[5, i, j] = s
                        R = so3d.exp(d) @ R_pred
                        for i, j in ti.ndrange(ns, ns):
                            s = ti.cast(0.0, f64)
                            for k in range(3):
                                s += work[5, i, k] * work[0, k, j]
                            work[4, i, j] = work[0, i, j] - s
                for i, j in ti.ndrange(ns, ns):
                    if i < j:
                        s = 0.5 * (work[4, i, j] + work[4, j, i])
                        work[4, i, j] = s
                        work[4, j, i] = s
            # re-orthonormalize (Gram-Schmidt on the columns)
            c0 = vec3d(R[0, 0], R[1, 0], R[2, 0]).normalized()
            c1 = vec3d(R[0, 1], R[1, 1], R[2, 1])
            c1 = (c1 - c0.dot(c1) * c0).normalized()
            c2 = c0.cross(c1)
            R = ti.Matrix.cols([c0, c1, c2])
            for i, j in ti.ndrange(ns, ns):
                state_P[0, i, j] = work[4, i, j]
            state_R[0] = R
            state_w[0] = w
            state_a[0] = a
            hist64[b] = R
            hist[b] = ti.cast(R, dtype)
            diag[b - b0, 0] = cnt[0]
            diag[b - b0, 1] = cnt[1]
            diag[b - b0, 2] = cnt[2]
            diag[b - b0, 3] = ti.max(work[4, 0, 0], ti.max(work[4, 1, 1], work[4, 2, 2]))
            diag[b - b0, 5] = kap_num
            diag[b - b0, 6] = kap_den
            diag[b - b0, 4] = cnt[3]

    return k_ekf_track


def _tdt(np_dtype):
    return ti.f64 if np.dtype(np_dtype) == np.float64 else ti.f32


def _c(a, dtype):
    return np.ascontiguousarray(a, dtype=dtype)


def select_references(hist, sel_R, b0: int, b1: int, batch_size: int, bearings, pix, pol, state: dict,
                      width: int, height: int, outlier_px: float, min_disp_px: float, max_lat_deg: float, ref_uv,
                      ref_n, ref_src=None, max_events: int = 0) -> None:
    """References of the events of batches b0..b1-1 (see module doc): batch b's events start at b * batch_size
    in ``bearings`` / ``pix`` / ``pol``, its selection pose is sel_R[b - b0], reference poses come from ``hist``
    (nb, 3, 3); fills ``ref_uv`` (n, 2), ``ref_n`` (n,) int32 (0: no measurement) and, when given, ``ref_src``
    (n,) int32 (the reference's batch) for those events and updates ``state`` (:func:`new_reference_state`). All
    arrays in the dtype of ``ref_uv`` (f32 or f64), C-contiguous."""
    ensure_init()
    dtype = ref_uv.dtype
    k = _select_kernel(_tdt(dtype))
    if ref_src is None:
        ref_src = np.zeros(len(ref_n), np.int32)
    if b1 > b0:
        k(hist, _c(np.asarray(sel_R).reshape(-1, 3, 3), dtype), int(b0), int(b1), int(batch_size), bearings, pix,
          pol, state["ref_b"], state["last_b"], state["last_p"], state["count"], int(width), int(height),
          float(width / (2 * np.pi)), float(height / np.pi), float(outlier_px) ** 2, float(min_disp_px) ** 2,
          _v_band(height, max_lat_deg), int(max_events), ref_uv, ref_n, ref_src)


def ekf_accumulate(R, bearings, ref_uv, ref_n, pol, grad, cov, updates, contrast: float, sigma: float,
                   huber: float, position_var: float = 0.0) -> np.ndarray:
    """Huber-weighted normal equations of one pose over a batch; the dtype of ``grad`` selects f32/f64.

    Returns N_ACC float64 sums (see ACC): H^T W H upper triangle, H^T W r, counts of valid / supported
    (bilinear weight of mapped pixels >= 1/2) / polarity-agreeing significant measurements (supported, |z_hat| above
    its std sqrt(S): the sign of a smaller prediction is noise, e.g. while the camera stops or turns back), sum of r^2/S over
    supported ones, sum of clipped squared normalized residuals, sums of p z_hat and of n over supported ones, count
    of significant ones.
    """
    ensure_init()
    dtype = grad.dtype
    k = _batch_kernels(_tdt(dtype))[0]
    out = np.zeros(N_ACC, np.float64)
    h, w = updates.shape
    if len(pol):
        k(_c(np.asarray(R).reshape(1, 3, 3), dtype), _c(np.asarray(bearings).reshape(-1, 3), dtype),
          _c(ref_uv, dtype), _c(ref_n, np.int32), _c(pol, np.int8), grad, cov, updates, int(w), int(h),
          float(w / (2 * np.pi)), float(h / np.pi), float(contrast), float(sigma) ** 2, float(position_var),
          float(huber), out)
    return out


def pf_loglik(particles, bearings, ref_uv, ref_n, pol, grad, cov, updates, contrast: float, sigma: float,
              floor: float, position_var: float = 0.0) -> np.ndarray:
    """(N,) float64 log-likelihood of a batch for each particle pose (N, 3, 3); dtype of ``grad`` selects f32/f64."""
    ensure_init()
    dtype = grad.dtype
    k = _batch_kernels(_tdt(dtype))[1]
    parts = _c(np.asarray(particles).reshape(-1, 3, 3), dtype)
    out = np.zeros(len(parts), np.float64)
    h, w = updates.shape
    if len(pol):
        k(parts, _c(np.asarray(bearings).reshape(-1, 3), dtype), _c(ref_uv, dtype), _c(ref_n, np.int32),
          _c(pol, np.int8), grad, cov, updates, int(w), int(h), float(w / (2 * np.pi)), float(h / np.pi),
          float(contrast), float(sigma) ** 2, float(position_var), float(floor), 1.0 / _SQRT_2PI, out)
    return out


def ekf_track(hist, hist64, mids, b0: int, b1: int, batch_size: int, bearings, pix, pol, state: dict, ref_uv, ref_n,
              grad, cov, updates, contrast: float, sigma: float, outlier_px: float, min_disp_px: float,
              max_lat_deg: float, huber: float, q_rate: float, q_min: float, q_acc: float, iterations: int, state_R,
              state_w, state_P, velocity_reference: bool = False, ref_src=None, max_events: int = 0, state_a=None,
              q_jerk: float = 0.0, position_var: float = 0.0) -> np.ndarray:
    """EKF-SMT on batches b0..b1-1 in one launch (see module doc and ``ekf_track_numpy``).

    ``hist`` (nb, 3, 3) in the map dtype and ``hist64`` (float64) receive the poses; ``state`` (per-pixel
    references), ``ref_uv`` / ``ref_n`` (per-event scratch, filled) as in :func:`select_references`;
    ``state_R`` ((1, 3, 3)), ``state_w`` ((1, 3), camera-frame angular velocity) and ``state_P`` ((1, 6, 6): pose
    error, velocity error), all float64, carry the filter between calls. ``state_a`` ((1, 3), camera-frame angular
    acceleration; then ``state_P`` is (1, 9, 9) and ``velocity_reference`` is required): the constant-acceleration
    model. Process noise per batch of duration dt: pose std max(q_rate dt, q_min), velocity std q_acc sqrt(dt),
    acceleration std q_jerk sqrt(dt) (q_acc = 0 with w = 0 and a zero velocity covariance: the random-walk model).
    ``velocity_reference`` (constant velocity or acceleration): state references (module doc) instead of the
    reference batch's estimated pose; ``ref_src`` (n,) int32 scratch (allocated when None). ``position_var``: the
    crossing-position variance (map px^2, module doc). Returns (b1 - b0, 7) diagnostics per batch: valid,
    supported and polarity-agreeing (significant) measurements, largest diagonal entry of the pose covariance
    (rad^2), significant measurements (see :func:`ekf_accumulate`), numerator and denominator of the innovation
    consistency kappa (module doc; 0 with pose references).
    """
    ensure_init()
    dtype = grad.dtype
    k = _track_kernel(_tdt(dtype))
    if ref_src is None:
        ref_src = np.zeros(len(ref_n), np.int32)
    ns = 6 if state_a is None else 9
    if ns == 9 and not velocity_reference:
        raise ValueError("the constant-acceleration model needs state references (velocity_reference)")
    if state_P.shape[1:] != (ns, ns):
        raise ValueError(f"state_P must be (1, {ns}, {ns}), got {state_P.shape}")
    if state_a is None:
        state_a, q_jerk = np.zeros((1, 3)), 0.0
    diag = np.zeros((max(b1 - b0, 0), 7), np.float64)
    if b1 > b0:
        h, w = updates.shape
        k(hist, hist64, mids, int(b0), int(b1), int(batch_size), bearings, pix, pol, state["ref_b"],
          state["last_b"], state["last_p"], state["count"], ref_uv, ref_n, ref_src, grad, cov, updates, int(w), int(h),
          float(w / (2 * np.pi)), float(h / np.pi), float(contrast), float(sigma) ** 2, float(position_var),
          float(outlier_px) ** 2,
          float(min_disp_px) ** 2, _v_band(h, max_lat_deg), int(max_events), float(huber), float(q_rate),
          float(q_min), float(q_acc), float(q_jerk), int(iterations), int(bool(velocity_reference)), state_R, state_w,
          state_a, state_P, np.zeros((8, 9, 9)), diag, ns)
    return diag


def ekf_predict_numpy(R, w, P, dt, q_rate, q_min, q_acc, a=None, q_jerk=0.0):
    """Constant-velocity (``a`` None, P 6x6) or constant-acceleration (P 9x9) prediction (float64):
    R exp(w dt + a dt^2 / 2), w + a dt, and P through F = [[I, R dt, R dt^2 / 2], [0, I, I dt], [0, 0, I]] plus
    noise. Returns (R, w, P)."""
    from ti_cmax import so3

    ns = 6 if a is None else 9
    a = np.zeros(3) if a is None else np.asarray(a, np.float64)
    R_pred = R @ so3.exp(w * dt + (0.5 * dt * dt * a if ns == 9 else 0.0))
    F = np.eye(ns)
    F[:3, 3:6] = R_pred * dt
    q = [max(q_rate * dt, q_min) ** 2] * 3 + [q_acc * q_acc * dt] * 3
    if ns == 9:
        F[:3, 6:] = 0.5 * dt * dt * R_pred
        F[3:6, 6:] = np.eye(3) * dt
        q += [q_jerk * q_jerk * dt] * 3
        w = w + a * dt
    return R_pred, np.array(w, np.float64), F @ P @ F.T + np.diag(q)


def ekf_track_numpy(hist, hist64, mids, b0, b1, batch_size, bearings, pix, pol, state, ref_uv, ref_n, grad, cov,
                    updates, contrast, sigma, outlier_px, min_disp_px, max_lat_deg, huber, q_rate, q_min, q_acc,
                    iterations, state_R, state_w, state_P, velocity_reference=False, ref_src=None, max_events=0,
                    state_a=None, q_jerk=0.0, position_var=0.0):
    """float64 twin of :func:`ekf_track` (same in/out arrays). With pose references the update is the iterated EKF
    (Gauss-Newton on prior + batch) for measurements of the pose only, x = P[:, :3] (I + Lam P_dd)^-1 (b + Lam d):
    equal to (P^-1 + E Lam E^T)^-1 (E b + E Lam d) with E = [I; 0] (tested), and defined when P is singular (the
    random-walk model has no velocity covariance). With state references the measurements depend on the whole
    state (6-d, or 9-d with the acceleration): (P^-1 + Lam) x = b + Lam x_j, posterior covariance (P^-1 + Lam)^-1."""
    from ti_cmax import so3

    h, w = updates.shape
    n = len(pol)
    ns = 6 if state_a is None else 9
    if ns == 6:
        q_jerk = 0.0  # no acceleration state: no jerk noise (as ekf_track)
    if ref_src is None:
        ref_src = np.zeros(len(ref_n), np.int32)
    diag = np.zeros((max(b1 - b0, 0), 7))
    for b in range(b0, b1):
        a_prev = None if ns == 6 else state_a[0].copy()
        R_pred, w_pred, P = ekf_predict_numpy(state_R[0], state_w[0], state_P[0], mids[b] - mids[b - 1], q_rate,
                                              q_min, q_acc, a_prev, q_jerk)
        x = np.zeros(ns)
        R, wv, av, lam = R_pred, w_pred, a_prev, np.zeros((3, 3))
        e0, e1 = b * batch_size, min((b + 1) * batch_size, n)
        select_references_numpy(hist, R_pred[None], b, b + 1, batch_size, bearings, pix, pol, state, w, h,
                                outlier_px, min_disp_px, max_lat_deg, ref_uv, ref_n, ref_src, max_events)
        acc = np.zeros(N_ACC)
        kap = (0.0, 0.0)
        if velocity_reference:
            post = P
            dtr = mids[b] - mids[ref_src[e0:e1]]
            for _ in range(iterations):
                ok, r, S, Hd, Hw, pred, sup = _measure_cv_numpy(
                    R, wv, dtr, bearings[e0:e1], ref_n[e0:e1], pol[e0:e1], grad, cov, updates, contrast,
                    sigma * sigma, q_acc * q_acc / 3.0, av, q_jerk * q_jerk / 20.0, pos2=position_var)
                nr = np.abs(r) / np.sqrt(S)
                wt = np.where(ok, np.where(nr <= huber, 1.0, huber / np.maximum(nr, 1e-300)) / S, 0.0)
                Hs = [Hd, Hw] + ([-0.5 * dtr[:, None] * Hw] if ns == 9 else [])
                Hn = np.concatenate(Hs, 1)
                supported = ok & (sup >= 0.5)
                pp = pred * np.asarray(pol[e0:e1], np.float64)
                significant = supported & (pp * pp > S)
                acc[9], acc[10], acc[11], acc[16] = ok.sum(), supported.sum(), (significant & (pp > 0)).sum(), \
                    significant.sum()
                if acc[9] > 0:
                    lamn = (Hn * wt[:, None]).T @ Hn
                    y = (Hn * wt[:, None]).T @ r
                    post = np.linalg.inv(np.linalg.inv(P) + lamn)
                    post = 0.5 * (post + post.T)
                    if _ == 0:  # innovation consistency (module doc), at the prediction
                        kap = (y @ post @ y - np.trace(post @ lamn @ P @ lamn), np.trace(post @ lamn))
                    x = post @ (y + lamn @ x)
                    R, wv = so3.exp(x[:3]) @ R_pred, w_pred + x[3:6]
                    if ns == 9:
                        av = a_prev + x[6:]
            P = post
        else:
            for _ in range(iterations):
                acc = ekf_accumulate_numpy(R, bearings[e0:e1], ref_uv[e0:e1], ref_n[e0:e1], pol[e0:e1], grad, cov,
                                           updates, contrast, sigma, huber, position_var)
                if acc[9] > 0:
                    lam = np.array([[acc[0], acc[1], acc[2]], [acc[1], acc[3], acc[4]], [acc[2], acc[4], acc[5]]])
                    x = P[:, :3] @ np.linalg.solve(np.eye(3) + lam @ P[:3, :3], acc[6:9] + lam @ x[:3])
                    R = so3.exp(x[:3]) @ R_pred
            wv = w_pred + x[3:6]
            E = np.zeros((ns, 3))
            E[:3] = np.eye(3)
            P = P - P @ E @ np.linalg.solve(np.eye(3) + lam @ P[:3, :3], lam) @ E.T @ P
            P = 0.5 * (P + P.T)
        u, _, vt = np.linalg.svd(R)
        R = u @ vt
        state_R[0], state_w[0], state_P[0] = R, wv, P
        if ns == 9:
            state_a[0] = av
        hist64[b] = R
        hist[b] = R
        diag[b - b0] = acc[9], acc[10], acc[11], np.max(np.diag(P)[:3]), acc[16], kap[0], kap[1]
    return diag


__all__ = ["ACC", "N_ACC", "new_reference_state", "select_references", "select_references_numpy", "ekf_accumulate",
           "ekf_accumulate_numpy", "pf_loglik", "pf_loglik_numpy", "ekf_track", "ekf_track_numpy",
           "ekf_predict_numpy"]
