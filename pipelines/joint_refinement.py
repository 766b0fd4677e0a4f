"""Joint refinement of the trajectory over many visits of the same regions: a BA of the map on stored events.

The sliding-window back-end aligns every new window to the global map, so once a region is mapped, later visits
follow that map, errors included: the error of the first turn of a pan repeats in every later turn. At a verified
revisit the loop closer (``pipelines/loop_closure.py``) calls :func:`refine_jointly`: the control poses from the first
stored stride on are refined together to maximize the variance of the panoramic IWE of the stored event subsamples of the
whole recording (Eq. 18 without the global map: every event is in the IWE, at the poses being refined), so each
visit's events sharpen the map of the others and the map is rebuilt from the result. The first pose stays fixed (it
anchors the world frame). The unknowns are increments at nodes a few window lengths apart, interpolated linearly
in time in between: the window BA leaves errors that vary slowly (the drift a turn builds up), which a chain of
every pose with only local gradients would take many iterations to reach.

The cost is bounded: at most ``max_events`` stored events (an even sample of each stride in proportion to the events
it stands for), in batches (one rotation each) of as many sampled events as arrive while the camera moves half a
map pixel (:func:`batch_size`: an evaluation costs about one spline evaluation per batch), a map of at most 2048
columns (a coarser level of larger panoramas), ``iterations`` L-BFGS iterations with every increment bounded by
``max_step`` (a pose that events barely constrain cannot run off).

:func:`refine_start` then registers the start of the trajectory against the map of the later stored events: the
first windows, few events against a young map, set the frame every later pose follows.
"""
from __future__ import annotations

import numpy as np

from ti_cmax import so3
from ti_cmax.kernels.pano import PanoIWE, batch_mid_times, vote_map

MAX_COLUMNS = 2048  # map columns of the joint refinement's IWE (larger panoramas: a coarser level)
BATCH_PX = 0.5  # map pixels the camera moves at most within a batch of sampled events (at its fastest rotation)


def sample_chunks(chunks, max_events: int) -> tuple[np.ndarray, np.ndarray, float]:
    """An even sample (times, bearings) of the stored strides (t, b, weight, ...): each stride keeps events in
    proportion to the events it stands for (len x weight), at most ``max_events`` in all; and the fraction kept."""
    stands_for = np.array([len(c[0]) * c[2] for c in chunks], dtype=float)
    total = float(stands_for.sum())
    if total <= 0:
        return np.zeros(0), np.zeros((0, 3), np.float32), 0.0
    frac = min(1.0, max_events / total)
    ts, bs = [], []
    for (t, b, *_), n in zip(chunks, stands_for):
        m = min(len(t), int(round(n * frac)))
        if m > 0:
            idx = np.unique(np.linspace(0, len(t) - 1, m).round().astype(np.int64))
            ts.append(t[idx])
            bs.append(b[idx])
    if not ts:
        return np.zeros(0), np.zeros((0, 3), np.float32), 0.0
    t, b = np.concatenate(ts), np.concatenate(bs)
    return t, b, len(t) / total


def batch_size(spline, first: int, last: int, times: np.ndarray, columns: int, least: float,
               motion_px: float = BATCH_PX) -> int:
    """Sampled events per batch (one rotation each): as many as arrive while the camera moves ``motion_px`` map
    pixels at its fastest rotation over poses first..last (the 99th percentile of the control poses' steps: one
    outlying step does not set it), and at least ``least`` (the back-end's batch span at the sampled rate). The
    cost of an evaluation grows with the number of batches (a spline evaluation with its Jacobians each), while the
    motion within a batch blurs the map only by a fraction of its blur."""
    ctrl = spline.control_R[first:last + 2]
    if len(times) < 2 or len(ctrl) < 2 or times[-1] <= times[0]:
        return max(1, int(round(least)))
    speed = float(np.percentile(so3.geodesic_angle(ctrl[:-1], ctrl[1:]), 99)) / spline.dt  # rad/s
    rate = len(times) / float(times[-1] - times[0])  # sampled events per second
    span = motion_px * 2 * np.pi / columns / speed if speed > 0 else float(times[-1] - times[0])
    return max(1, int(round(least)), int(span * rate))


def map_level(width: int, height: int) -> int:
    """The power-of-two factor that brings the map to at most MAX_COLUMNS columns (dividing both sides)."""
    f = 1
    while width // f > MAX_COLUMNS and width % (2 * f) == 0 and height % (2 * f) == 0:
        f *= 2
    return f


def refine_jointly(spline, chunks, first: int, last: int, backend_cfg, width: int, height: int, *,
                   max_events: int, iterations: int, max_step: float, coarse_spacing: float,
                   fine_iterations: int = 0, slice_point=lambda: None, hold_mean: bool = False):
    """Left increments x (last - first + 1, 3) of the control poses first..last of ``spline`` (later poses follow
    the last one rigidly, earlier ones stay) maximizing the variance of the IWE of the stored strides ``chunks``:
    ``iterations`` L-BFGS iterations on increments interpolated between nodes every ``coarse_spacing`` seconds
    (zero at pose ``first``), then ``fine_iterations`` on every pose; and a summary (events, evaluations, variance
    gain, largest change in degrees). ``slice_point`` is called before every cost evaluation (the loop closer's
    sliced execution in real time). ``hold_mean``: the nodes' increments are kept at zero mean (the rotation common
    to them projected out): when no fixed pose but the first holds the world frame, the stored events of the first
    instants (a camera starting slowly gives few) tie that common rotation only weakly, so the refinement
    redistributes the errors along the trajectory and leaves its mean orientation to the window BA."""
    from scipy.optimize import minimize  # here: ~0.3 CPU s of import that a run without a verified revisit skips

    # the setup pauses too (sampling, the batches' supports, the problem's arrays): in real time each step of it
    # runs in its own slice, between the windows
    slice_point()
    t, b, frac = sample_chunks(chunks, max_events)
    slice_point()
    m = last - first + 1
    info = {"events": int(len(t)), "poses": int(m), "evaluations": 0, "gain": 1.0, "max_change_deg": 0.0}
    if len(t) == 0 or m <= 0:
        return np.zeros((max(m, 0), 3)), info
    f = map_level(width, height)
    batch = batch_size(spline, first, last, t, width // f, backend_cfg.event_batch_size * frac)
    info["batch"] = batch
    start, end = spline.valid_time_range()
    s, u = spline.support(np.clip(batch_mid_times(t, batch), start, end))
    slice_point()
    problem = PanoIWE(b, s, u, spline.degree, width // f, height // f, sigma=backend_cfg.backend_blur_sigma,
                      alpha=0.0, batch_size=batch)
    base = spline.control_R.copy()
    n = len(base)
    scale = []

    def objective(z):
        slice_point()
        x = z.reshape(m, 3)
        inc = np.zeros((n, 3))
        inc[first:last + 1] = x
        inc[last + 1:] = x[-1]
        var, grad = problem.cost_and_grad(so3.exp(inc) @ base)
        if not scale:
            scale.append(1.0 / var if var > 0 else 1.0)
        g = grad[first:last + 1].copy()
        g[-1] += grad[last + 1:].sum(axis=0)
        g = np.einsum("nji,nj->ni", so3.left_jacobian(x), g)  # d var / d x: Jl(x)^T times the left gradient
        info["evaluations"] += 1
        return -var * scale[0], -g.reshape(-1) * scale[0]

    # coarse: increments interpolated linearly in time between nodes every coarse_spacing, zero at the first
    # pose; a chain of poses with only local gradients converges slowly on its smooth, long-wavelength errors
    # (the drift a turn builds up), which these few unknowns reach in a few iterations
    interp = _interpolation(spline.knot_times()[first:last + 1], coarse_spacing)
    x = np.zeros((m, 3))
    if interp is not None and hold_mean and interp.shape[1] > 1:  # x = interp (I - 11^T / k) z: zero node mean
        interp = interp - interp.mean(axis=1, keepdims=True)
    if interp is not None:
        def coarse(z):
            f, g = objective((interp @ z.reshape(-1, 3)).reshape(-1))
            return f, (interp.T @ g.reshape(m, 3)).reshape(-1)

        k = interp.shape[1]
        res = minimize(coarse, np.zeros(3 * k), jac=True, method="L-BFGS-B", bounds=[(-max_step, max_step)] * (3 * k),
                       options={"maxiter": int(iterations), "maxcor": 20})
        x = interp @ res.x.reshape(k, 3)
        info["gain"] = float(-res.fun)
    if fine_iterations > 0:  # fine: every pose, from the coarse result
        res = minimize(objective, x.reshape(-1), jac=True, method="L-BFGS-B",
                       bounds=[(-max_step, max_step)] * (3 * m), options={"maxiter": int(fine_iterations), "maxcor": 20})
        x = res.x.reshape(m, 3)
        info["gain"] = float(-res.fun)
    info["max_change_deg"] = float(np.degrees(np.linalg.norm(x, axis=1).max()))
    return x, info


def _start_layout(spline, chunks, min_events: float, spacing: float, span: float):
    """refine_start's nodes: (t_n, j, interp) with t_n the time the stored strides reach ``min_events`` events, j the
    last control pose the start moves and interp the (j + 1, free nodes) linear interpolation of the nodes'
    increments (the last node is zero); None when the span runs past the spline."""
    stands_for = np.cumsum([len(c[0]) * c[2] for c in chunks])
    k = min(int(np.searchsorted(stands_for, min_events)), len(chunks) - 1)
    c_t, c_n = chunks[k][0], stands_for[k] - (stands_for[k - 1] if k else 0.0)
    need = min_events - (stands_for[k - 1] if k else 0.0)  # events still needed within stride k
    t_n = float(c_t[min(int(need / c_n * len(c_t)), len(c_t) - 1)]) if len(c_t) and c_n > 0 else chunks[k][3]
    nodes = t_n + spacing * np.arange(max(int(round(span / spacing)), 1) + 1)
    knots = spline.knot_times()
    j = min(int(np.searchsorted(knots, nodes[-1], side="left")) - 1, spline.num_control - 1)
    if j < 0 or nodes[-1] > spline.valid_time_range()[1]:
        return None
    interp = np.zeros((j + 1, len(nodes) - 1))  # poses 0..j x free nodes (the last node is zero)
    m = np.clip(np.searchsorted(nodes, knots[:j + 1], side="right") - 1, 0, len(nodes) - 2)
    w = np.clip((knots[:j + 1] - nodes[m]) / spacing, 0.0, 1.0)
    interp[np.arange(j + 1), m] = 1 - w
    inner = m + 1 < len(nodes) - 1
    interp[np.flatnonzero(inner), m[inner] + 1] = w[inner]
    return t_n, j, interp


def refine_start(spline, chunks, min_events: float, spacing: float, span: float, backend_cfg, width: int,
                 height: int, *, max_events: int, iterations: int, max_step: float, slice_point=lambda: None):
    """Left increments y (j + 1, 3) of the control poses 0..j that shape the trajectory's start, maximizing
    Var(B(I_start) + B(I_rest)) with the later poses fixed: the stored events those poses move (I_start) registered
    against the map of an even sample of the others (I_rest, at most ``max_events``, voted once at their poses and
    weighted for the events they stand for); and a summary.

    A camera that starts slowly gives the first windows few events while their map is young, so their poses are set
    by little data against little map, and every later pose inherits their error through the map: aligned at the
    start, the whole trajectory carries it as a constant rotation. Against the map the later visits built, the start
    joins the rest. The increments are interpolated linearly between nodes every ``spacing`` seconds from the time
    t_n the stored strides reach ``min_events`` events (the events of a window the back-end deems enough), zero from
    t_n + ``span`` on; the poses before t_n move with the first node, as one block: their few events (a still start
    gives sensor noise alone) would turn each of them at random. The later poses hold the world frame."""
    from scipy.optimize import minimize

    slice_point()
    info = {"events": 0, "poses": 0, "evaluations": 0, "gain": 1.0, "max_change_deg": 0.0}
    layout = _start_layout(spline, chunks, min_events, spacing, span) if chunks and span > 0 else None
    if layout is None:
        return np.zeros((0, 3)), info
    t_n, j, interp = layout
    start, end = spline.valid_time_range()
    knots = spline.knot_times()
    # the strides that may hold events whose pose depends on a free control pose (the later ones only feed the map)
    n_loc = int(np.searchsorted([c[3] for c in chunks], knots[j] + (spline.degree + 1) * spline.dt, side="right"))
    t = np.concatenate([c[0] for c in chunks[:n_loc]])
    b = np.concatenate([c[1] for c in chunks[:n_loc]])
    wt = np.concatenate([np.full(len(c[0]), c[2]) for c in chunks[:n_loc]])
    local = (t >= start) & (t <= end)
    local[local] = spline.support(t[local])[0] <= j
    t_loc, b_loc = t[local], b[local]
    if len(t_loc) == 0:
        return np.zeros((j + 1, 3)), info
    rest = [(c[0][c[0] > t_loc[-1]], c[1][c[0] > t_loc[-1]], c[2]) for c in chunks[:n_loc]] + chunks[n_loc:]
    t_map, b_map, frac = sample_chunks([c for c in rest if len(c[0]) and c[0][0] <= end], max_events)
    ok = (t_map >= start) & (t_map <= end)
    t_map, b_map = t_map[ok], b_map[ok]
    info.update(events=int(len(t_loc)), map_events=int(len(t_map)), poses=int(j + 1), t_n=t_n - start)
    if len(t_map) == 0:
        return np.zeros((j + 1, 3)), info
    f = map_level(width, height)
    cols, rows = width // f, height // f
    slice_point()
    # the map of the rest: its sampled events at their fixed poses, each vote standing for 1 / frac events
    map_batch = batch_size(spline, j, spline.num_control - 1, t_map, cols, backend_cfg.event_batch_size * frac)
    rest_raw = vote_map(b_map, spline.evaluate(np.clip(batch_mid_times(t_map, map_batch), start, end)), cols, rows,
                        batch_size=map_batch)
    rest_raw /= np.float32(frac)
    slice_point()
    loc_frac = len(t_loc) / float(wt[local].sum())  # the stored fraction of the events they stand for
    batch = batch_size(spline, 0, j, t_loc, cols, backend_cfg.event_batch_size * loc_frac)
    s, u = spline.support(np.clip(batch_mid_times(t_loc, batch), start, end))
    problem = PanoIWE(b_loc, s, u, spline.degree, cols, rows, sigma=backend_cfg.backend_blur_sigma,
                      global_map=rest_raw, alpha=1.0, batch_size=batch)
    base = spline.control_R.copy()
    scale = []

    def objective(z):
        slice_point()
        y = interp @ z.reshape(-1, 3)
        ctrl = base.copy()
        ctrl[:j + 1] = so3.exp(y) @ base[:j + 1]
        var, grad = problem.cost_and_grad(ctrl)
        if not scale:
            scale.append(1.0 / var if var > 0 else 1.0)
        g = np.einsum("nji,nj->ni", so3.left_jacobian(y), grad[:j + 1])
        info["evaluations"] += 1
        return -var * scale[0], -(interp.T @ g).reshape(-1) * scale[0]

    k = interp.shape[1]
    res = minimize(objective, np.zeros(3 * k), jac=True, method="L-BFGS-B", bounds=[(-max_step, max_step)] * (3 * k),
                   options={"maxiter": int(iterations), "maxcor": 20})
    y = interp @ res.x.reshape(k, 3)
    info["gain"] = float(-res.fun)
    info["max_change_deg"] = float(np.degrees(np.linalg.norm(y, axis=1).max()))
    return y, info


def _interpolation(times: np.ndarray, spacing: float) -> np.ndarray | None:
    """(len(times), k) matrix of linear interpolation between nodes every ``spacing`` from times[0] (the first
    node's column dropped: zero there); None when the span holds no second node."""
    if spacing <= 0 or len(times) < 2:
        return None
    nodes = times[0] + spacing * np.arange(int(np.ceil((times[-1] - times[0]) / spacing)) + 1)
    if len(nodes) < 2:
        return None
    j = np.clip(np.searchsorted(nodes, times, side="right") - 1, 0, len(nodes) - 2)
    w = (times - nodes[j]) / spacing
    a = np.zeros((len(times), len(nodes)))
    a[np.arange(len(times)), j] = 1 - w
    a[np.arange(len(times)), j + 1] = w
    return a[:, 1:]
