"""Accuracy and map-quality metrics of the paper's Sec. IV-B (Eq. 21-24) and the star-tracking metric.

Pure numpy/scipy on :class:`~ti_cmax.trajectory.Trajectory`, no I/O (the ``evaluate`` command and the
benchmarks read files and call these).

* Absolute error (Eq. 21): angle of R_gt(t)^T R_est(t) at the estimate's timestamps, or on a fixed-rate grid
  (50 Hz for continuous trajectories), ground truth interpolated by Slerp, both restricted to the time range
  the two trajectories share; the estimate is first aligned at t0: R_est(t) <- R_gt(t0) R_est(t0)^T R_est(t).
* Relative error (Eq. 22): angle of (R_gt(t)^T R_gt(t+d))^T (R_est(t)^T R_est(t+d)) for pairs t, t + d
  (d = 1 s) whose start t steps every 0.1 s from the start of the overlap, divided by d (deg/s).
* Angles (Eq. 23) are geodesic, computed as |log(B)| (same value as arccos((tr B - 1)/2), stable near 0).
* Optional Gaussian low-pass filter of the ground truth on SO(3) (paper: 50 ms, for noisy mocap).
* Event area EA% (lambda0 = 1) and gradient magnitude GM (Eq. 24) of an image of warped events.
* Star tracking (Chin et al.): angle between estimated and true relative rotations over 400 ms, RMSE and std.
* Long recordings: the worst stretch (largest RMS of the absolute error over any 0.2 s) and the absolute error per
  revolution of a pan (its mean per part of each turn: an error that depends on where the camera points swings
  once per turn; its mean per turn shows whether later turns differ from the first).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import so3
from .config import Params, param
from .errors import InputError
from .trajectory import Trajectory

CONTINUOUS_RATE_HZ = 50.0  # rate at which continuous (spline) trajectories are evaluated
T0_OFFSET_SYNTHETIC = 0.1  # alignment time after the start of the overlap, synthetic sequences (s)
T0_OFFSET_REAL = 1.0  # same for real recordings (s)
GT_FILTER_SPAN = 0.05  # time span of the Gaussian low-pass filter applied to mocap ground truth (s)
STAR_WINDOW = 0.4  # interval of the star-tracking relative-rotation metric (s)
WORST_WINDOW = 0.2  # span of the worst stretch of a long recording (s)
TURN_SECTORS = 4  # parts of a turn over which the per-revolution error is averaged (quarter turns)
_EPS_T = 1e-9


@dataclass(frozen=True)
class EvaluationConfig(Params):
    """Parameters of :func:`evaluate_rotations` (also the ``--config``/``--set`` keys of ``ti-cmax evaluate``)."""

    t0_offset: float = param(T0_OFFSET_SYNTHETIC, "t0 = start of the overlap + this (unless --t0 is given)", unit="s",
                             ge=0)
    align: bool = param(True, "align the estimate to the ground truth at t0")
    sample_rate: float = param(0.0, "rate of the absolute-error grid", unit="Hz", gt=0,
                               zero="the estimate's own timestamps")
    rel_delta: float = param(1.0, "time span of the relative-error pairs", unit="s", gt=0)
    rel_step: float = param(0.1, "spacing of the relative-error pair starts", unit="s", gt=0)
    gt_filter_span: float = param(0.0, "Gaussian low-pass span on the ground truth (0: off)", unit="s", ge=0)


@dataclass(frozen=True, eq=False)
class RotationErrors:
    """Absolute (deg) and relative (deg/s) rotation errors of one estimate, summaries plus per-sample arrays."""

    abs_rmse_deg: float
    abs_mean_deg: float
    abs_median_deg: float
    abs_max_deg: float
    rel_rmse_deg_per_s: float
    rel_mean_deg_per_s: float
    rel_median_deg_per_s: float
    rel_max_deg_per_s: float
    num_abs: int
    num_rel: int
    t0: float
    aligned: bool
    rel_delta: float
    t_start: float  # overlap of the two trajectories
    t_end: float
    abs_times: np.ndarray
    abs_errors_deg: np.ndarray
    rel_times: np.ndarray  # start time of each pair
    rel_errors_deg_per_s: np.ndarray

    def to_dict(self) -> dict:
        """JSON-ready scalars (NaN, e.g. no relative pair fits in a short overlap, becomes None)."""
        out = {}
        for name in ("abs_rmse_deg", "rel_rmse_deg_per_s", "abs_mean_deg", "abs_median_deg", "abs_max_deg",
                     "rel_mean_deg_per_s", "rel_median_deg_per_s", "rel_max_deg_per_s", "num_abs", "num_rel",
                     "t0", "aligned", "rel_delta", "t_start", "t_end"):
            v = getattr(self, name)
            if isinstance(v, float) and not np.isfinite(v):
                v = None
            out[name] = v
        return out


@dataclass(frozen=True, eq=False)
class RelativeRotationErrors:
    """Star-tracking metric: angle (deg) between estimated and true relative rotations over ``window`` s."""

    rmse_deg: float
    std_deg: float
    mean_deg: float
    count: int
    window: float
    times: np.ndarray  # start time of each interval
    errors_deg: np.ndarray

    def to_dict(self) -> dict:
        out = {"rmse_deg": self.rmse_deg, "std_deg": self.std_deg, "mean_deg": self.mean_deg,
               "count": self.count, "window": self.window}
        return {k: (None if isinstance(v, float) and not np.isfinite(v) else v) for k, v in out.items()}


# ------------------------------------------------------------------------------------------
# building blocks
# ------------------------------------------------------------------------------------------

def rotation_angle_deg(r: np.ndarray) -> np.ndarray:
    """Geodesic angle (Eq. 23) of rotation matrices (..., 3, 3), in degrees."""
    return np.degrees(np.linalg.norm(so3.log(r), axis=-1))


def time_overlap(a: Trajectory, b: Trajectory) -> tuple[float, float]:
    """Time range covered by both trajectories; InputError if they share none."""
    lo, hi = max(a.t_start, b.t_start), min(a.t_end, b.t_end)
    if hi < lo:
        raise InputError(
            f"trajectories do not overlap in time ([{a.t_start:.6f}, {a.t_end:.6f}] s vs "
            f"[{b.t_start:.6f}, {b.t_end:.6f}] s)")
    return lo, hi


def default_t0(groundtruth: Trajectory, estimate: Trajectory, offset: float = T0_OFFSET_SYNTHETIC) -> float:
    """Alignment time: start of the overlap + ``offset`` (0.1 s synthetic, 1.0 s real), kept inside it."""
    lo, hi = time_overlap(groundtruth, estimate)
    return float(min(lo + offset, hi))


def absolute_errors_deg(groundtruth: Trajectory, estimate: Trajectory, times: np.ndarray) -> np.ndarray:
    """Eq. 21/23: angle of R_gt(t)^T R_est(t) at ``times`` (deg); no alignment here."""
    times = np.asarray(times, dtype=float)
    return rotation_angle_deg(np.swapaxes(groundtruth.at(times), -1, -2) @ estimate.at(times))


def relative_pair_starts(t_start: float, t_end: float, delta: float = 1.0, step: float = 0.1) -> np.ndarray:
    """Starts t_k = t_start + k * step of all pairs (t_k, t_k + delta) inside [t_start, t_end]."""
    if delta <= 0 or step <= 0:
        raise InputError(f"relative-error delta and step must be positive (got {delta}, {step})")
    span = t_end - t_start - delta
    if span < -_EPS_T:
        return np.zeros(0)
    n = int(np.floor(max(span, 0.0) / step + 1e-6)) + 1
    return t_start + step * np.arange(n)


def relative_errors_deg(groundtruth: Trajectory, estimate: Trajectory, starts: np.ndarray,
                        delta: float) -> np.ndarray:
    """Eq. 22/23: angle of (G_k^T G_k+d)^T (E_k^T E_k+d) for each start (deg, not divided by delta)."""
    starts = np.asarray(starts, dtype=float)
    if len(starts) == 0:
        return np.zeros(0)
    gt_rel = np.swapaxes(groundtruth.at(starts), -1, -2) @ groundtruth.at(starts + delta)
    est_rel = np.swapaxes(estimate.at(starts), -1, -2) @ estimate.at(starts + delta)
    return rotation_angle_deg(np.swapaxes(gt_rel, -1, -2) @ est_rel)


def smooth_trajectory(traj: Trajectory, span: float = GT_FILTER_SPAN) -> Trajectory:
    """Gaussian low-pass filter on SO(3) with a kernel covering ``span`` seconds (sigma = span / 4, cut at 2 sigma).

    For each sample i the neighbours are lifted to the tangent space at R_i, phi_j = log(R_i^T R_j), a
    Gaussian-weighted local-linear fit phi(tau) = a + b tau is made in the time offset tau = t_j - t_i, and
    R_i exp(a) is returned. Inside the trajectory (uniform sampling) a is the plain Gaussian-weighted mean;
    the linear term removes the lag a one-sided window would add at the two ends. Constant-rate rotations
    pass unchanged. Non-uniform timestamps are handled (weights use times, not indices).
    """
    if span <= 0 or len(traj) < 3:
        return traj
    t, r = traj.t, traj.R
    n = len(t)
    sigma = span / 4.0
    half = 2.0 * sigma
    idx = np.arange(n)
    lo = np.searchsorted(t, t - half - _EPS_T, side="left")
    hi = np.searchsorted(t, t + half + _EPS_T, side="right")  # neighbours are [lo, hi)
    k_max = int(max(np.max(idx - lo), np.max(hi - 1 - idx)))
    s0 = np.zeros(n)
    s1 = np.zeros(n)
    s2 = np.zeros(n)
    s_phi = np.zeros((n, 3))
    s_tphi = np.zeros((n, 3))
    r_t = np.swapaxes(r, -1, -2)
    for k in range(-k_max, k_max + 1):
        j = idx + k
        valid = (j >= lo) & (j < hi)
        jj = np.clip(j, 0, n - 1)
        tau = t[jj] - t
        w = np.where(valid, np.exp(-0.5 * (tau / sigma) ** 2), 0.0)
        phi = so3.log(r_t @ r[jj]) if k != 0 else np.zeros((n, 3))
        s0 += w
        s1 += w * tau
        s2 += w * tau * tau
        s_phi += w[:, None] * phi
        s_tphi += (w * tau)[:, None] * phi
    det = s0 * s2 - s1 * s1
    ok = det > 1e-9 * np.maximum(s0 * s2, 1e-300)
    safe = np.where(ok, det, 1.0)
    a = np.where(ok[:, None], (s2[:, None] * s_phi - s1[:, None] * s_tphi) / safe[:, None],
                 s_phi / s0[:, None])
    return Trajectory(t, r @ so3.exp(a))


def _summary(x: np.ndarray) -> tuple[float, float, float, float]:
    if len(x) == 0:
        return (float("nan"),) * 4
    return (float(np.sqrt(np.mean(x * x))), float(np.mean(x)), float(np.median(x)), float(np.max(x)))


# ------------------------------------------------------------------------------------------
# the evaluations
# ------------------------------------------------------------------------------------------

def evaluate_rotations(groundtruth: Trajectory, estimate: Trajectory, *, t0: float | None = None,
                       t0_offset: float = T0_OFFSET_SYNTHETIC, align: bool = True,
                       sample_rate: float | None = None, rel_delta: float = 1.0, rel_step: float = 0.1,
                       gt_filter_span: float | None = None) -> RotationErrors:
    """Absolute and relative rotation errors of ``estimate`` against ``groundtruth`` (Sec. IV-B).

    ``t0``: alignment time (default: start of the overlap + ``t0_offset``). ``sample_rate``: None/0 evaluates
    the absolute error at the estimate's timestamps, a rate (e.g. CONTINUOUS_RATE_HZ) on a grid from the
    start of the overlap. ``gt_filter_span``: smooth the ground truth first (:func:`smooth_trajectory`).
    """
    if gt_filter_span:
        groundtruth = smooth_trajectory(groundtruth, gt_filter_span)
    lo, hi = time_overlap(groundtruth, estimate)
    if t0 is None:
        t0 = default_t0(groundtruth, estimate, t0_offset)
    elif not (lo - _EPS_T <= t0 <= hi + _EPS_T):
        raise InputError(f"t0 = {t0} s lies outside the time range both trajectories cover [{lo:.6f}, {hi:.6f}] s")
    t0 = float(t0)
    est = estimate.aligned_to(groundtruth, t0) if align else estimate

    if sample_rate:
        times = lo + np.arange(int(np.floor((hi - lo) * sample_rate + 1e-6)) + 1) / sample_rate
    else:
        times = est.t[(est.t >= lo - _EPS_T) & (est.t <= hi + _EPS_T)]
    if len(times) == 0:
        raise InputError("the estimate has no timestamp inside the ground truth's time range")
    abs_err = absolute_errors_deg(groundtruth, est, times)

    starts = relative_pair_starts(lo, hi, rel_delta, rel_step)
    rel_err = relative_errors_deg(groundtruth, est, starts, rel_delta) / rel_delta

    a, r = _summary(abs_err), _summary(rel_err)
    return RotationErrors(
        abs_rmse_deg=a[0], abs_mean_deg=a[1], abs_median_deg=a[2], abs_max_deg=a[3],
        rel_rmse_deg_per_s=r[0], rel_mean_deg_per_s=r[1], rel_median_deg_per_s=r[2], rel_max_deg_per_s=r[3],
        num_abs=int(len(abs_err)), num_rel=int(len(rel_err)), t0=t0, aligned=bool(align),
        rel_delta=float(rel_delta), t_start=float(lo), t_end=float(hi),
        abs_times=np.asarray(times, dtype=float), abs_errors_deg=abs_err,
        rel_times=starts, rel_errors_deg_per_s=rel_err,
    )


# a ground truth and an estimate are compared only when the ground truth has this many poses inside the time range
# both cover (an error interpolated between 2 poses measures the interpolation: 8.8 deg reported with exit 0), the
# estimate MIN_ESTIMATE_POSES, and their median time steps are within MAX_STEP_RATIO of each other (microseconds against
# seconds: 1e6; a 1 kHz ground truth against a 50 Hz estimate: 20)
MIN_GROUNDTRUTH_POSES = 3
MIN_ESTIMATE_POSES = 2
MAX_STEP_RATIO = 1000.0


def check_comparable(groundtruth: Trajectory, estimate: Trajectory) -> None:
    """Raise InputError (one line) when ``estimate`` cannot be scored against ``groundtruth``: time steps that differ
    in scale, no overlap, or too few poses over the overlap."""
    steps = []
    for name, traj in (("ground truth", groundtruth), ("estimate", estimate)):
        d = np.diff(traj.t)
        steps.append((name, float(np.median(d)) if len(d) else None))
    (_, g), (_, e) = steps
    if g and e and max(g / e, e / g) > MAX_STEP_RATIO:
        raise InputError(f"the time ranges differ in scale: the ground truth's poses are {g:.3g} s apart (median), the "
                         f"estimate's {e:.3g} s ({max(g / e, e / g):.3g}x): are both in seconds? (e.g. microseconds "
                         f"against seconds)")
    lo, hi = time_overlap(groundtruth, estimate)
    for name, traj, least in (("ground truth", groundtruth, MIN_GROUNDTRUTH_POSES),
                              ("estimate", estimate, MIN_ESTIMATE_POSES)):
        inside = int(np.count_nonzero((traj.t >= lo - _EPS_T) & (traj.t <= hi + _EPS_T)))
        if inside < least:
            raise InputError(f"the {name} has {inside} pose{'s' if inside != 1 else ''} in the time range both "
                             f"trajectories cover [{lo:.6f}, {hi:.6f}] s, at least {least} are needed to compare them")


def evaluate_with_config(groundtruth: Trajectory, estimate: Trajectory, cfg: EvaluationConfig,
                         t0: float | None = None) -> RotationErrors:
    """:func:`evaluate_rotations` with parameters from an :class:`EvaluationConfig`, after
    :func:`check_comparable` (the commands' entry point)."""
    check_comparable(groundtruth, estimate)
    return evaluate_rotations(groundtruth, estimate, t0=t0, t0_offset=cfg.t0_offset, align=cfg.align,
                              sample_rate=cfg.sample_rate or None, rel_delta=cfg.rel_delta,
                              rel_step=cfg.rel_step, gt_filter_span=cfg.gt_filter_span or None)


def star_tracking_errors(groundtruth: Trajectory, estimate: Trajectory, window: float = STAR_WINDOW,
                         step: float | None = None) -> RelativeRotationErrors:
    """Angle between R_est(t)^T R_est(t+window) and the same for the ground truth (deg), RMSE and std.

    Pairs start every ``step`` s (default: ``window``, i.e. back-to-back intervals) over the overlap. No
    alignment is needed: relative rotations do not change when a trajectory is left-multiplied.
    """
    lo, hi = time_overlap(groundtruth, estimate)
    starts = relative_pair_starts(lo, hi, window, step or window)
    err = relative_errors_deg(groundtruth, estimate, starts, window)
    if len(err):
        rmse, std, mean = float(np.sqrt(np.mean(err * err))), float(np.std(err)), float(np.mean(err))
    else:
        rmse = std = mean = float("nan")
    return RelativeRotationErrors(rmse_deg=rmse, std_deg=std, mean_deg=mean, count=int(len(err)),
                                  window=float(window), times=starts, errors_deg=err)


# ------------------------------------------------------------------------------------------
# long recordings
# ------------------------------------------------------------------------------------------

def worst_stretch(times: np.ndarray, errors_deg: np.ndarray, window: float = WORST_WINDOW) -> tuple[float, float]:
    """(RMS, start time) of the window [t, t + window] (t a sample time) where the errors' RMS is largest: a short
    failure that an RMSE over a minute dilutes. Windows lie inside the samples' time range (the whole range when
    it is shorter than ``window``); (nan, nan) without samples."""
    t, e = np.asarray(times, dtype=float), np.asarray(errors_deg, dtype=float)
    if len(t) == 0:
        return float("nan"), float("nan")
    csum = np.concatenate([[0.0], np.cumsum(e * e)])
    starts = np.flatnonzero(t <= t[-1] - window + _EPS_T)
    if len(starts) == 0:
        starts = np.array([0])
    ends = np.searchsorted(t, t[starts] + window + _EPS_T, side="right")
    rms = np.sqrt((csum[ends] - csum[starts]) / (ends - starts))
    k = int(np.argmax(rms))
    return float(rms[k]), float(t[starts[k]])


def pan_angle_deg(groundtruth: Trajectory, times: np.ndarray) -> np.ndarray:
    """Angle (deg) the camera has turned about its own vertical axis (camera y, the simulator's pan axis) since the
    ground truth's start, at ``times``: the y components of the body-frame rotations between consecutive ground-truth
    poses, summed. A pan's turns are counted even when a wobble has tilted that axis away from the world vertical
    (over a minute it can turn the camera upside down: the pan goes on about the tilted axis)."""
    step = so3.log(np.swapaxes(groundtruth.R[:-1], -1, -2) @ groundtruth.R[1:])[:, 1]
    turned = np.concatenate([[0.0], np.cumsum(step)])
    return np.degrees(np.interp(np.asarray(times, dtype=float), groundtruth.t, turned))


@dataclass(frozen=True, eq=False)
class RevolutionErrors:
    """The absolute error per revolution of a pan: ``means_deg[k]`` over turn k (the last one possibly partial,
    ``turns[k]`` of a turn covered), ``sector_means_deg[k, j]`` over part j of it (nan: no sample). ``swing_deg``:
    the largest max - min of the part means within one complete turn (an error that follows where the camera
    points); ``spread_deg``: max - min of the complete turns' means (later turns against the first). Both nan
    without a complete turn."""

    means_deg: np.ndarray
    turns: np.ndarray
    sector_means_deg: np.ndarray
    swing_deg: float
    spread_deg: float
    complete: int  # number of complete turns

    def to_dict(self) -> dict:
        fin = lambda v: float(v) if np.isfinite(v) else None  # noqa: E731
        return {"means_deg": [fin(v) for v in self.means_deg], "turns": [float(v) for v in self.turns],
                "sector_means_deg": [[fin(v) for v in row] for row in self.sector_means_deg],
                "swing_deg": fin(self.swing_deg), "spread_deg": fin(self.spread_deg), "complete": self.complete}


def revolution_errors(groundtruth: Trajectory, times: np.ndarray, errors_deg: np.ndarray,
                      sectors: int = TURN_SECTORS) -> RevolutionErrors:
    """The absolute errors ``errors_deg`` at ``times`` (e.g. ``RotationErrors.abs_errors_deg``, start-aligned)
    grouped by the revolution of the pan (:func:`pan_angle_deg`) made since ``times[0]`` (in its overall direction)
    and by ``sectors`` equal parts of each turn (see :class:`RevolutionErrors`)."""
    if sectors < 1:
        raise InputError(f"sectors must be at least 1, got {sectors}")
    t, e = np.asarray(times, dtype=float), np.asarray(errors_deg, dtype=float)
    if len(t) == 0:
        nan = float("nan")
        return RevolutionErrors(np.zeros(0), np.zeros(0), np.zeros((0, sectors)), nan, nan, 0)
    pan = pan_angle_deg(groundtruth, t)
    progress = np.maximum((pan - pan[0]) * (1.0 if pan[-1] >= pan[0] else -1.0), 0.0) / 360.0
    turn = np.floor(progress).astype(int)
    part = np.minimum(((progress - turn) * sectors).astype(int), sectors - 1)
    n = int(turn.max()) + 1
    complete = int(np.floor(progress.max()))
    count = np.zeros((n, sectors))
    total = np.zeros((n, sectors))
    np.add.at(count, (turn, part), 1.0)
    np.add.at(total, (turn, part), e)
    with np.errstate(invalid="ignore"):
        sector_means = total / count
    means = total.sum(axis=1) / count.sum(axis=1)
    covered = np.minimum(progress.max() - np.arange(n), 1.0)
    if complete:
        full = sector_means[:complete]
        swing = float(np.nanmax(np.nanmax(full, axis=1) - np.nanmin(full, axis=1)))
        spread = float(np.ptp(means[:complete]))
    else:
        swing = spread = float("nan")
    return RevolutionErrors(means, covered, sector_means, swing, spread, complete)


# ------------------------------------------------------------------------------------------
# map quality (Sec. IV-B3)
# ------------------------------------------------------------------------------------------

BLOCK_PIXELS = 1 << 21  # figures of large maps (an 8192x4096 HD map) are summed over row blocks of about this size


def row_blocks(shape, halo: int = 0):
    """(rows with halo, interior rows relative to them) covering an image by blocks of about BLOCK_PIXELS pixels:
    float64 temporaries of an 8192x4096 map would be 270 MB each."""
    h = shape[0]
    step = max(1, BLOCK_PIXELS // max(1, int(np.prod(shape[1:]))))
    for r0 in range(0, h, step):
        r1 = min(h, r0 + step)
        a, b = max(0, r0 - halo), min(h, r1 + halo)
        yield slice(a, b), slice(r0 - a, r1 - a)


def event_area_percent(image: np.ndarray, lambda0: float = 1.0) -> float:
    """EA% = 100 * sum(1 - exp(-H(x) / lambda0)) / number of pixels, for an image of warped events H >= 0."""
    image = np.asarray(image)
    if image.size == 0:
        raise InputError("event area of an empty image")
    total = sum(float(np.sum(-np.expm1(-np.asarray(image[rows], dtype=np.float64) / lambda0)))
                for rows, _ in row_blocks(image.shape))
    return 100.0 * total / image.size


def local_texture(image: np.ndarray, sigma: float, wrap_columns: bool = True) -> np.ndarray:
    """Band-pass texture of an image, normalized by its local RMS: (H - G_s H) / sqrt(G_s (H - G_s H)^2), G_s a
    Gaussian of std ``sigma`` px (columns wrap for panoramas). Correlating two such images compares structure, not
    exposure: a map region observed for longer, or only partly, does not lower the correlation. The blur is the
    project's (kernels/blur.py, OpenCV's SIMD filter, truncated like scipy's: scipy's filters took 8 ms per call on a
    0.2 M pixel box in loop closure's confidence test); zeros beyond the borders."""
    from ti_cmax.kernels.blur import gaussian_taps, separable_blur

    img = np.asarray(image, dtype=np.float64)
    taps = gaussian_taps(sigma)
    hp = img - separable_blur(img, taps, wrap_cols=wrap_columns)
    rms = np.sqrt(np.maximum(separable_blur(hp * hp, taps, wrap_cols=wrap_columns), 0.0))
    return hp / (rms + 1e-3 * float(rms.max()) + 1e-300)


def image_gradient(image: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(I_x, I_y) by Sobel, divided by 8 so that a ramp of slope 1 per pixel gives 1; borders replicated."""
    import cv2  # (scipy.ndimage.sobel gives the same to rounding; importing scipy.ndimage cost ~0.2 s per command)

    img = np.asarray(image, dtype=np.float64)
    gx = cv2.Sobel(img, cv2.CV_64F, 1, 0, ksize=3, borderType=cv2.BORDER_REFLECT)
    return gx / 8.0, cv2.Sobel(img, cv2.CV_64F, 0, 1, ksize=3, borderType=cv2.BORDER_REFLECT) / 8.0


def gradient_magnitude(image: np.ndarray) -> float:
    """GM (Eq. 24) = sqrt(mean over pixels of |grad I|^2), gradient from :func:`image_gradient` (by row blocks with
    a one-row halo: the same sum as on the whole image, in bounded memory)."""
    image = np.asarray(image)
    if image.size == 0:
        raise InputError("gradient magnitude of an empty image")
    total = 0.0
    for rows, inner in row_blocks(image.shape, halo=1):
        gx, gy = image_gradient(image[rows])
        total += float(np.sum(gx[inner] ** 2 + gy[inner] ** 2))
    return float(np.sqrt(total / image.size))


__all__ = [
    "CONTINUOUS_RATE_HZ", "T0_OFFSET_SYNTHETIC", "T0_OFFSET_REAL", "GT_FILTER_SPAN", "STAR_WINDOW",
    "EvaluationConfig", "RotationErrors", "RelativeRotationErrors", "check_comparable",
    "rotation_angle_deg", "time_overlap", "default_t0", "absolute_errors_deg", "relative_pair_starts",
    "relative_errors_deg", "smooth_trajectory", "evaluate_rotations", "evaluate_with_config",
    "star_tracking_errors", "event_area_percent", "image_gradient", "gradient_magnitude", "WORST_WINDOW",
    "TURN_SECTORS", "worst_stretch", "pan_angle_deg", "RevolutionErrors", "revolution_errors",
]
