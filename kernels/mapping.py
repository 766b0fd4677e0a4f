"""Per-map-pixel EKF on the log-intensity gradient (mapping module of SMT, paper App. B, Eq. 38), Taichi + numpy twin.

State per panorama pixel m: gradient g_m = (dM/du, dM/dv) of the log intensity M in map pixels, its 2x2
covariance P_m (stored as P00, P01, P11), the number of visits and the time of its last update.
State per SENSOR pixel: the map point (u, v) and time of its previous event.

Measurement of an event e_k at sensor pixel x_k with polarity p_k (Eq. 38): the brightness at x_k changed by
p_k C since the previous event at x_k, while the map point under x_k moved by dp = p_m(t_k) - p_m(t_k - dt_k).
With constant gradient between the two map points,

    z = p_k C,    h(g) = g . dp  ( = -g . v dt_k, v = -dp / dt_k the apparent velocity of the scene point
                                   relative to the sensor pixel, i.e. the optical flow in map coordinates).

The sign makes g the gradient of M itself (M(p_m(t_k)) - M(p_m(t_k - dt_k)) = p_k C). The update goes to the map
pixel nearest to the midpoint of the two map points (where the finite difference is centred); it is rejected as
an outlier when |dp| > ``outlier_px``. A map pixel's updates are grouped in visits (a new visit starts when more
than ``visit_gap`` seconds passed since its last update; visit_gap <= 0 counts every update as a visit); a pixel
stops updating after ``cap`` visits (cap <= 0: no limit). Scalar EKF update, H = dp^T, R = sigma_z^2:
    S = H P H^T + R,  K = P H^T / S,  g <- g + K (z - H g),  P <- P - P H^T H P / S.

Events go in the order given (the updates of a pixel depend on its previous ones), so the update kernel runs as
one serialized loop: bit-reproducible, no atomics. The pose of event e is ``rotations[e // batch_size]``.
f32 is the production path (polynomial atan2 of kernels/pano), f64 the reference path; ``ekf_update_numpy``
is the float64 oracle.
"""

import functools

import numpy as np

from .pano import _proj_funcs, equirect_numpy
from .runtime import ensure_init, ti

# stats slots returned by the update functions
STATS = ("updates", "outliers", "capped", "first_at_pixel", "still", "outside")
NO_TIME = -1.0e300  # "no previous event" marker of the per-sensor-pixel memory


def new_map_state(width: int, height: int, num_sensor_pixels: int, initial_variance: float, dtype=np.float32):
    """Zero gradients with covariance initial_variance * I, empty sensor memory; a dict of numpy arrays."""
    cov = np.zeros((height, width, 3), dtype)
    cov[..., 0] = initial_variance
    cov[..., 2] = initial_variance
    return {
        "grad": np.zeros((height, width, 2), dtype),
        "cov": cov,
        "visits": np.zeros((height, width), np.int32),
        "updates": np.zeros((height, width), np.int32),
        "last_t": np.full((height, width), NO_TIME, np.float64),
        "mem_uv": np.zeros((num_sensor_pixels, 2), dtype),
        "mem_t": np.full(num_sensor_pixels, NO_TIME, np.float64),
    }


def sensor_index(x: np.ndarray, y: np.ndarray, sensor_width: int) -> np.ndarray:
    """Linear sensor-pixel index y * W + x (sub-pixel coordinates rounded to the nearest pixel)."""
    xi = np.floor(np.asarray(x, np.float64) + 0.5).astype(np.int64) if np.issubdtype(np.asarray(x).dtype, np.floating) \
        else np.asarray(x, np.int64)
    yi = np.floor(np.asarray(y, np.float64) + 0.5).astype(np.int64) if np.issubdtype(np.asarray(y).dtype, np.floating) \
        else np.asarray(y, np.int64)
    return np.ascontiguousarray(yi * sensor_width + xi, dtype=np.int32)


# ----------------------------------------------------------------------------------------------------------------
# numpy twin (float64 oracle)
# ----------------------------------------------------------------------------------------------------------------
def ekf_update_numpy(state: dict, bearings, rotations, batch_size: int, t, p, pix, width: int, height: int,
                     contrast: float, sigma_z: float, outlier_px: float, cap: int, visit_gap: float) -> np.ndarray:
    """Per-event loop in float64 on ``state`` (modified in place); returns the STATS counts."""
    b = np.asarray(bearings, np.float64).reshape(-1, 3)
    rot = np.asarray(rotations, np.float64).reshape(-1, 3, 3)
    xw = np.einsum("nij,nj->ni", rot[np.arange(len(b)) // batch_size], b)
    u, v = equirect_numpy(xw, width, height)
    g, P, visits, updates, last_t = state["grad"], state["cov"], state["visits"], state["updates"], state["last_t"]
    mem_uv, mem_t = state["mem_uv"], state["mem_t"]
    r = sigma_z * sigma_z
    stats = np.zeros(len(STATS), np.int64)
    half = 0.5 * width
    for e in range(len(b)):
        k = pix[e]
        had = mem_t[k] > 0.5 * NO_TIME
        u0, v0 = float(mem_uv[k, 0]), float(mem_uv[k, 1])
        mem_uv[k] = (u[e], v[e])
        mem_t[k] = t[e]
        if not had:
            stats[3] += 1
            continue
        du = u[e] - u0
        dv = v[e] - v0
        if du > half:
            du -= width
        elif du <= -half:
            du += width
        d2 = du * du + dv * dv
        if d2 > outlier_px * outlier_px:
            stats[1] += 1
            continue
        if d2 < 1e-12:
            stats[4] += 1
            continue
        col = int(np.floor(u0 + 0.5 * du + 0.5)) % width
        row = int(np.floor(v0 + 0.5 * dv + 0.5))
        if row < 0 or row >= height:
            stats[5] += 1
            continue
        if visit_gap <= 0 or t[e] - last_t[row, col] > visit_gap:
            visits[row, col] += 1
        if cap > 0 and visits[row, col] > cap:
            stats[2] += 1
            continue
        last_t[row, col] = t[e]
        p00, p01, p11 = P[row, col]
        ph0 = p00 * du + p01 * dv
        ph1 = p01 * du + p11 * dv
        s = du * ph0 + dv * ph1 + r
        innov = p[e] * contrast - (g[row, col, 0] * du + g[row, col, 1] * dv)
        g[row, col, 0] += ph0 / s * innov
        g[row, col, 1] += ph1 / s * innov
        P[row, col] = (p00 - ph0 * ph0 / s, p01 - ph0 * ph1 / s, p11 - ph1 * ph1 / s)
        updates[row, col] += 1
        stats[0] += 1
    return stats


# ----------------------------------------------------------------------------------------------------------------
# Taichi kernel
# ----------------------------------------------------------------------------------------------------------------
@functools.cache
def _update_kernel(dtype):
    project, _ = _proj_funcs(dtype)
    vec3 = ti.types.vector(3, dtype)
    mat3 = ti.types.matrix(3, 3, dtype)

    @ti.kernel
    def k_update(
        bearings: ti.types.ndarray(dtype=vec3, ndim=1),
        rotations: ti.types.ndarray(dtype=mat3, ndim=1),
        batch_size: ti.i32,
        t: ti.types.ndarray(dtype=ti.f64, ndim=1),
        p: ti.types.ndarray(dtype=ti.i8, ndim=1),
        pix: ti.types.ndarray(dtype=ti.i32, ndim=1),
        width: ti.i32,
        height: ti.i32,
        su: dtype,
        sv: dtype,
        contrast: dtype,
        r_noise: dtype,
        outlier2: dtype,
        cap: ti.i32,
        visit_gap: ti.f64,
        grad: ti.types.ndarray(dtype=dtype, ndim=3),
        cov: ti.types.ndarray(dtype=dtype, ndim=3),
        visits: ti.types.ndarray(dtype=ti.i32, ndim=2),
        updates: ti.types.ndarray(dtype=ti.i32, ndim=2),
        last_t: ti.types.ndarray(dtype=ti.f64, ndim=2),
        mem_uv: ti.types.ndarray(dtype=dtype, ndim=2),
        mem_t: ti.types.ndarray(dtype=ti.f64, ndim=1),
        stats: ti.types.ndarray(dtype=ti.i64, ndim=1),
    ):
        half = ti.cast(width, dtype) * ti.cast(0.5, dtype)
        wf = ti.cast(width, dtype)
        ti.loop_config(serialize=True)
        for e in range(bearings.shape[0]):
            x = rotations[e // batch_size] @ bearings[e]
            pu, pv = project(x, width, height, su, sv)
            k = pix[e]
            had = mem_t[k] > ti.f64(0.5 * NO_TIME)
            u0 = mem_uv[k, 0]
            v0 = mem_uv[k, 1]
            mem_uv[k, 0] = pu
            mem_uv[k, 1] = pv
            mem_t[k] = t[e]
            if not had:
                stats[3] += 1
                continue
            du = pu - u0
            dv = pv - v0
            if du > half:
                du -= wf
            elif du <= -half:
                du += wf
            d2 = du * du + dv * dv
            if d2 > outlier2:
                stats[1] += 1
                continue
            if d2 < ti.cast(1e-12, dtype):
                stats[4] += 1
                continue
            col = ti.cast(ti.floor(u0 + ti.cast(0.5, dtype) * du + ti.cast(0.5, dtype)), ti.i32)
            row = ti.cast(ti.floor(v0 + ti.cast(0.5, dtype) * dv + ti.cast(0.5, dtype)), ti.i32)
            col = col % width
            if col < 0:
                col += width
            if row < 0 or row >= height:
                stats[5] += 1
                continue
            if visit_gap <= 0 or t[e] - last_t[row, col] > visit_gap:
                visits[row, col] += 1
            if cap > 0 and visits[row, col] > cap:
                stats[2] += 1
                continue
            last_t[row, col] = t[e]
            p00 = cov[row, col, 0]
            p01 = cov[row, col, 1]
            p11 = cov[row, col, 2]
            ph0 = p00 * du + p01 * dv
            ph1 = p01 * du + p11 * dv
            s = du * ph0 + dv * ph1 + r_noise
            innov = ti.cast(p[e], dtype) * contrast - (grad[row, col, 0] * du + grad[row, col, 1] * dv)
            grad[row, col, 0] += ph0 / s * innov
            grad[row, col, 1] += ph1 / s * innov
            cov[row, col, 0] = p00 - ph0 * ph0 / s
            cov[row, col, 1] = p01 - ph0 * ph1 / s
            cov[row, col, 2] = p11 - ph1 * ph1 / s
            updates[row, col] += 1
            stats[0] += 1

    return k_update


def ekf_update(state: dict, bearings, rotations, batch_size: int, t, p, pix, width: int, height: int,
               contrast: float, sigma_z: float, outlier_px: float, cap: int, visit_gap: float) -> np.ndarray:
    """Taichi twin of :func:`ekf_update_numpy`; the dtype of ``state['grad']`` (f32 or f64) selects the path.

    ``rotations`` (nb, 3, 3): pose of event e is rotations[e // batch_size]. Returns the STATS counts.
    """
    ensure_init()
    dtype = state["grad"].dtype
    n = len(t)
    stats = np.zeros(len(STATS), np.int64)
    if n == 0:
        return stats
    tdt = ti.f64 if dtype == np.float64 else ti.f32
    kernel = _update_kernel(tdt)
    rot = np.ascontiguousarray(np.asarray(rotations).reshape(-1, 3, 3), dtype=dtype)
    if len(rot) < -(-n // batch_size):
        raise ValueError(f"{len(rot)} rotations for {n} events in batches of {batch_size}")
    kernel(np.ascontiguousarray(np.asarray(bearings).reshape(-1, 3), dtype=dtype), rot, int(batch_size),
           np.ascontiguousarray(t, np.float64), np.ascontiguousarray(p, np.int8), np.ascontiguousarray(pix, np.int32),
           int(width), int(height), float(width / (2 * np.pi)), float(height / np.pi), float(contrast),
           float(sigma_z) ** 2, float(outlier_px) ** 2, int(cap), float(visit_gap),
           state["grad"], state["cov"], state["visits"], state["updates"], state["last_t"], state["mem_uv"],
           state["mem_t"], stats)
    return stats


def warm_up(dtype=np.float32) -> None:
    """Compile (or load from the offline cache) the update kernel of ``dtype`` on a one-event dummy map, so
    that runtime measurements of the first real call do not include it."""
    state = new_map_state(4, 2, 1, 1.0, dtype)
    ekf_update(state, np.array([[0.0, 0.0, 1.0]]), np.eye(3)[None], 1, np.zeros(1), np.ones(1, np.int8),
               np.zeros(1, np.int32), 4, 2, 0.2, 0.05, 10.0, 0, 0.0)


__all__ = ["STATS", "NO_TIME", "new_map_state", "sensor_index", "ekf_update", "ekf_update_numpy", "warm_up"]
