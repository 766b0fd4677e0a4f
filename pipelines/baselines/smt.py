"""SMT baseline (Kim et al. BMVC 2014, as re-implemented by the paper, Sec. II-A, App. B): simultaneous mosaicing
and tracking with a particle-filter (PF-SMT) or an error-state EKF (EKF-SMT) tracker.

Mapping: :class:`~ti_cmax.pipelines.workflows.grayscale.GrayscaleMapper` (per-pixel EKF on the log-intensity gradient,
Eq. 38, outliers beyond 10 map px, 5 visits cap; Poisson M only for the output map), fed the tracked poses in
chunks of ``map_update_events`` events, lagging the tracker (parallel tracking and mapping). Tracking: events
in batches of ``batch_size`` sharing one pose R (world_from_camera); the brightness increment of a sensor pixel
along its map segment is predicted from the GRADIENT map, z_hat = g(p_mid) . dp, and compared with p n C
(kernels/baselines/smt.py). Bootstrap: for the first ``bootstrap_seconds`` the poses come from IMU dead reckoning
(started at the ground-truth pose when it is known) or from ground truth when there is no IMU. C: App. B's values (0.2
synthetic: the simulator's from simulation.json; 0.22 real).

Where this departs from App. B / [12], [57] and why (rationale with figures: docs/design.md, SMT baselines):

* Gradient map instead of a refreshed Poisson M in the measurement: it is what the mapping EKFs estimate (same
  sign and scale of g), current after every map update (no solve, no refresh lag, no smoothing-in of unmapped
  areas), and it carries a covariance, so unmapped or unconverged pixels weigh little (S = n sigma^2 +
  dp^T P_g dp).
* A motion state, not a random walk on R (``motion_model``). Each event measures the motion since an earlier event
  of its pixel, relative to the pose estimated then: a random-walk prior, which says "no motion since the last
  batch", shrinks every weakly observed velocity component toward zero (roll about the optical axis carries several
  times less information per batch than pan and tilt), and the relative measurements never undo the lag.
  ``motion_model=random_walk`` keeps App. B's model.
* State references (``reference=velocity``, kernels/baselines/smt.py): the reference point of a segment is predicted
  from the state being estimated, p(R exp(-w dt_ref) b), not taken from the pose estimated for the reference's batch
  (``reference=pose``). A pose reference is an earlier estimate taken as exact: the pose std shrinks far below the
  error and reference errors feed back into the pose until it runs away. The state reference makes the increment a
  measurement of the angular velocity, as Eq. 38 writes it (h = -g . v dt), with the constant-velocity
  extrapolation's variance (q_acc^2 dt_ref^3 / 3 per axis) in S; the update is 6-d.
* Constant-acceleration EKF (the default ``motion_model=constant_acceleration``, state R, w, a;
  kernels/baselines/smt.py): a reference segment dt_ref long measures the mean angular velocity over it,
  w - a dt_ref / 2; a constant-velocity state reads it as the current w, so its velocity lags under angular
  acceleration, and its velocity random walk (``angular_acceleration_std``) can only trade that lag for noise.
  ``constant_velocity`` keeps that model.
* Acceleration steps per batch, not per second (``acceleration_step_std`` s_b = 10 rad/s^2): the acceleration is a
  random walk whose step has the std s_b in every batch, whatever the batch lasts; the kernel gets the jerk
  intensity q_j = s_b / sqrt(dt) at each call's mean batch duration dt (report ``angular_jerk_std_range``). Every
  batch carries about the same information (``batch_size`` events under the same noise model), and a Kalman
  filter's gains are set by the process noise per update against the measurement noise per update (the tracking
  index of Bar-Shalom, Li & Kirubarajan, Estimation with Applications to Tracking and Navigation, 2001, ch. 6), so a
  fixed step per batch gives the filter a memory of a fixed number of events at any event rate. The event rate grows
  with the apparent speed (the events per radian turned are set by the texture), so per batch is nearly per angle
  turned; a fixed intensity per second makes the filter stiffest where the camera moves fastest. The value is about
  the rms angular acceleration per axis of the simulated motion (6-11 rad/s^2): each batch's prior lets the
  acceleration move by its own size, and the segments of the last few batches say where it is.
  ``acceleration_step_std=0`` uses ``angular_jerk_std`` per second instead.
* Crossing-position noise in S (``crossing_position_var`` = 1/6, i.e. 2 x 1/12 map px^2, kernels/baselines/smt.py):
  each end of a segment is a level crossing somewhere within its map pixel (uniform: variance 1/12 px^2 per end), so
  the increment read from the gradient is uncertain by |g|^2 / 6, on top of n sigma^2 and the map's dp^T P_g dp. A
  rule from the map's resolution, not a tuned value. Without it the regressor z_hat carries the map's error while S
  does not grow with |g|, so the fitted speed is attenuated (errors in variables), a bias no innovation test sees.
* Segments also end after ``max_segment_events`` (2) events: the length test uses the estimated motion, so after
  a missed stop or turn-back an estimate "at rest" lets no segment reach 1 map px and the events only grow n.
* Reference segments of at least ``min_displacement_px`` (1 map px) instead of the previous event: the map
  holds pixel-averaged gradients and events fire where the gradient is steep, so segments shorter than a pixel
  have their increment under-predicted; the tracker reads that as a motion scale error, which it integrates into
  drift. The events of a short segment are summed (n C), nothing is dropped.
* EKF-SMT: reference segments of at most ``max_segment_px`` (2 map px; PF-SMT keeps the mapper's 10 px outlier
  distance, below): a longer segment restarts at its event without a measurement. z_hat = g(p_mid) . dp reads the
  bilinear gradient map at the midpoint, whose stencil reaches one pixel either side of it, so a segment whose ends
  lie farther than 1 px from its midpoint integrates gradient the model does not read. And a segment grows long only
  because its pixel's brightness hardly changed (it is selected by the quantity it measures), so its increment is
  over-predicted. The length sets the segment's age (length / speed), and the constant-acceleration state would read
  a bias that changes with the age as an acceleration. PF-SMT's state has no velocity or acceleration for such a
  bias to go into, so it keeps the long segments' information.
* No measurements beyond ``max_latitude_deg`` (70 deg): the equirectangular chart is singular at the poles
  (u stretches by 1 / cos(lat)). The map frame stays the world frame of App. B.
* Map gain: at the end of the bootstrap (known poses) the ratio k of the observed increments p n C to the
  predicted g . dp is measured and C, sigma are divided by it (:func:`_calibrate_gain`). The mapping EKF and the
  tracker read g differently (nearest pixel of each event's midpoint vs bilinear along longer segments), and a
  wrong scale is a velocity bias that the relative measurements integrate into drift.
* The motion-consistency loss check below (the paper reports failures by inspection).

* EKF-SMT: error-state EKF, update with Huber-weighted normal equations of the batch (iterated
  ``ekf_iterations`` times), see kernels/baselines/smt.py.
* PF-SMT: ``num_particles`` poses, random walk exp(n) R with n ~ N(0, (sigma_w dt)^2 I), weights times
  prod_k (N(r_k; 0, S_k) + floor), systematic resampling when the effective sample size drops below
  ``pf_resample_ess`` N; estimate = weighted mean on SO(3); numpy Generator seeded by ``seed``; references
  selected under the previous estimate.

Tracking loss, judged over a sliding window of ``loss_window`` s once tracking started: too few measurements land
on mapped pixels (map support), the significant predicted increments (|z_hat| above its std: at a stop or a
turn-back the others have no sign worth counting) agree in sign with the polarities barely more often than chance
(likelihood collapse), or the estimate diverges (pose std, angular speed, non-finite values). These are the
filter's own statistics, and a tracker that feeds its map can jump or drift far while they stay healthy (high
support and agreement); so the tracker's angular velocity is also checked against the events by contrast
maximization (:class:`~ti_cmax.pipelines.baselines.consistency.MotionConsistencyCheck`): its contrast ratio catches
large velocity errors, and its slow-drift test a steady smaller error (``consistency_drift_*``: the tracker's motion
against the contrast optimum, integrated over 0.6 s; every 0.2 s of it must drift by more than 1.5 deg).
The result then has status "lost", ``lost_at`` (start of the window that failed) and a trajectory that ends there.
"""
from __future__ import annotations

import dataclasses
import math
import time
from collections import deque
from dataclasses import dataclass
from typing import Iterable, Iterator

import numpy as np

from ti_cmax import so3
from ti_cmax.camera import Camera
from ti_cmax.config import Params, param
from ti_cmax.errors import InputError
from ti_cmax.events import Events
from ti_cmax.kernels import mapping as km
from ti_cmax.kernels.baselines import smt as ks
from ti_cmax.kernels.pano import batch_mid_times
from ti_cmax.trajectory import Trajectory

from ti_cmax.pipelines.frontend import as_chunks
from ti_cmax.pipelines.workflows.grayscale import GrayscaleConfig, GrayscaleMapper, GrayscaleResult, resolve_contrast
from .consistency import MotionConsistencyCheck
from .imu import dead_reckoning
from .result import BaselineResult

TRACKERS = ("ekf", "pf")
MOTION_MODELS = ("constant_acceleration", "constant_velocity", "random_walk")
REFERENCES = ("velocity", "pose")


@dataclass(frozen=True)
class SmtConfig(Params):
    """Parameters of SMT (load with ``load_config(SmtConfig, ...)``; mapping keys as ``mapping.<name>``)."""

    tracker: str = param("ekf", "tracker: ekf (EKF-SMT) or pf (PF-SMT)", choices=TRACKERS)
    batch_size: int = param(100, "events sharing one tracker pose (EKF-SMT)", unit="events", ge=1)
    pf_batch_size: int = param(200, "same for PF-SMT (~num_particles times the EKF's cost per batch)", unit="events",
                               ge=1)
    bootstrap_seconds: float = param(0.5, "poses from IMU dead reckoning (or ground truth) at the start", unit="s",
                                     ge=0)
    measurement_sigma: float = param(0.1, "std of z = p C around the predicted increment (log intensity)", gt=0)
    min_displacement_px: float = param(1.0, "shortest reference segment (module doc; < 0.05: per event)",
                                       unit="map px", ge=0)
    max_segment_px: float = param(2.0, "EKF-SMT: longest reference segment that is a measurement (longer ones "
                                         "restart without one; module doc; PF-SMT: the mapper's outlier distance)",
                                  unit="map px", gt=0)
    max_segment_events: int = param(2, "a reference segment also ends after this many events (module doc; 0: "
                                            "only by length)", ge=0)
    max_latitude_deg: float = param(70.0, "no measurements beyond this latitude (the map's chart is singular at "
                                          "the poles)", unit="deg", ge=0)
    motion_model: str = param("constant_acceleration", "EKF motion model: constant_acceleration (state R, w, a; "
                              "module doc), constant_velocity (R, w) or random_walk (R only)", choices=MOTION_MODELS)
    reference: str = param("velocity", "EKF reference point of a segment: velocity (moves with the state: its "
                           "error is the velocity error x dt; constant_velocity only) or pose (the reference batch's "
                           "estimated pose, taken as exact)", choices=REFERENCES)
    angular_acceleration_std: float = param(20.0, "constant_velocity: w random walk, std per batch = this x "
                                                  "sqrt(dt)", gt=0)
    acceleration_step_std: float = param(10.0, "constant_acceleration: std of the acceleration's random-walk step "
                                         "per batch, whatever the batch's duration (module doc; 0: angular_jerk_std "
                                         "per second instead)", unit="rad/s^2", ge=0)
    angular_jerk_std: float = param(1000.0, "constant_acceleration with acceleration_step_std 0: a random walk, std "
                                           "per batch = this x sqrt(dt) (module doc)", gt=0)
    acceleration_velocity_std: float = param(2.0, "constant_acceleration: w random walk, std per batch = this x "
                                                  "sqrt(dt) (module doc)", ge=0)
    pose_noise_std: float = param(0.0, "constant_velocity: extra pose step std per batch = this x dt",
                                  unit="rad/s", ge=0)
    initial_velocity_std: float = param(0.5, "std of w at the end of the bootstrap (constant_velocity, "
                                        "constant_acceleration)", unit="rad/s", ge=0)
    initial_acceleration_std: float = param(20.0, "std of the angular acceleration at the end of the bootstrap "
                                            "(constant_acceleration; its mean is 0)", unit="rad/s^2", gt=0)
    angular_velocity_std: float = param(4.0, "random-walk (and PF) step std per batch = this x batch duration",
                                        unit="rad/s", gt=0)
    min_step_std: float = param(2e-4, "floor of the pose step std (random walk, PF)", unit="rad", gt=0)
    initial_std_deg: float = param(0.3, "std of the pose at the end of the bootstrap", unit="deg", gt=0)
    ekf_iterations: int = param(2, "Gauss-Newton iterations of the EKF update per batch", ge=1)
    huber: float = param(2.0, "EKF: Huber threshold on normalized residuals", gt=0)
    num_particles: int = param(100, "PF-SMT particles", ge=1)
    pf_outlier_density: float = param(0.05, "PF: floor added to each event's Gaussian likelihood (robustness)", gt=0)
    pf_resample_ess: float = param(0.5, "resample when ESS < this x num_particles", ge=0, le=1)
    seed: int = param(0, "random seed of the particle filter")
    crossing_position_var: float = param(1.0 / 6.0, "variance of where a segment's two level crossings lie within "
                                         "their map pixels: S += this |g|^2 (module doc: 1/6 = 2 x 1/12; 0: off)",
                                         unit="map px^2", ge=0)
    gain_calibration_seconds: float = param(0.1, "end of the bootstrap that calibrates the map gain (0: gain 1)",
                                            unit="s", ge=0)
    map_update_events: int = param(5000, "tracked events buffered before the mapping EKFs take them", unit="events",
                                   ge=1)
    chunk_events: int = param(1_000_000, "events per streamed chunk (the first one spans the bootstrap)",
                              unit="events", ge=1)
    loss_window: float = param(0.1, "sliding window of the loss checks", unit="s", gt=0)
    loss_min_measurements: int = param(200, "measurements in the window needed to judge support and agreement", ge=0)
    loss_min_support: float = param(0.1, "lost below this fraction of measurements on mapped pixels", ge=0, le=1)
    loss_min_agreement: float = param(0.55, "lost below this fraction of significant measurements (supported, "
                                            "|z_hat| above its std) of matching sign",
                                      ge=0, le=1)
    loss_max_std_deg: float = param(5.0, "lost above this pose std (EKF covariance / particle spread)", unit="deg",
                                    gt=0)
    loss_max_angular_velocity: float = param(50.0, "lost above this angular velocity over the window", unit="rad/s",
                                             gt=0)
    # motion consistency (baselines/consistency.py): every consistency_interval s, the contrast of the events of a
    # consistency_span window warped with the tracker's angular velocity, over the best contrast near it; lost when
    # the mean of the last consistency_checks ratios is below consistency_min_ratio (0 interval: off)
    consistency_interval: float = param(0.05, "time between motion-consistency checks (0: off)", unit="s", ge=0)
    consistency_span: float = param(0.04, "events of this span judge the tracker's angular velocity", unit="s", gt=0)
    consistency_min_ratio: float = param(0.9, "lost when the mean contrast ratio of the last checks is below this",
                                         ge=0, le=1)
    consistency_checks: int = param(2, "checks averaged by that rule", ge=1)
    # slow drift (baselines/consistency.py): lost when, over the last consistency_drift_horizon s split into
    # consistency_drift_parts parts, every part drifts from the events' motion by more than consistency_drift_deg
    consistency_drift_horizon: float = param(0.6, "horizon of the slow-drift test (0: off)", unit="s", ge=0)
    consistency_drift_parts: int = param(3, "the drift must exceed the threshold in each of this many parts of the "
                                            "horizon (a steady error, not a transient)", ge=1)
    consistency_drift_deg: float = param(1.5, "slow-drift threshold per part", unit="deg", gt=0)
    mapping: GrayscaleConfig = param(help="the mapping EKFs", factory=lambda: GrayscaleConfig(
        outlier_distance_px=10.0, max_updates_per_pixel=5, pano_height=512))


@dataclass
class SmtResult:
    trajectory: Trajectory  # poses at the batch mid-times, up to lost_at when tracking was lost
    map: GrayscaleResult  # .log_intensity, .to_uint8() for the PNG
    report: dict  # status ("ok" | "lost"), lost_at, lost_reason, events_processed, wall_seconds, us_per_event, ...

    @property
    def status(self) -> str:
        return self.report["status"]


def smt_contrast(config: SmtConfig, dataset_path=None) -> float:
    """C: mapping.contrast_threshold if set, else the simulator's (0.2) next to a simulated dataset, else 0.22."""
    return resolve_contrast(config.mapping, dataset_path)


# ------------------------------------------------------------------------------------------------------------
# small SO(3) helpers (3x3, hot path)
# ------------------------------------------------------------------------------------------------------------
def _exp1(phi: np.ndarray) -> np.ndarray:
    th = math.sqrt(float(phi @ phi))
    k = np.array([[0.0, -phi[2], phi[1]], [phi[2], 0.0, -phi[0]], [-phi[1], phi[0], 0.0]])
    if th < 1e-8:
        return np.eye(3) + k
    return np.eye(3) + (math.sin(th) / th) * k + ((1 - math.cos(th)) / (th * th)) * (k @ k)


def _orthonormalize(r: np.ndarray) -> np.ndarray:
    u, _, vt = np.linalg.svd(r)
    return u @ vt


def weighted_mean_rotation(rotations: np.ndarray, weights: np.ndarray, iterations: int = 2) -> np.ndarray:
    """Weighted Karcher mean of (N, 3, 3) rotations (left perturbations), started at the heaviest one."""
    mean = rotations[int(np.argmax(weights))]
    for _ in range(iterations):
        d = so3.log(rotations @ mean.T)
        mean = _exp1(weights @ d) @ mean
    return mean


def systematic_resample(weights: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Indices of a systematic resampling of normalized ``weights`` (one uniform draw)."""
    n = len(weights)
    positions = (rng.random() + np.arange(n)) / n
    cum = np.cumsum(weights)
    cum[-1] = 1.0
    return np.minimum(np.searchsorted(cum, positions, side="right"), n - 1)


# ------------------------------------------------------------------------------------------------------------
# trackers: one batch at a time
# ------------------------------------------------------------------------------------------------------------
@dataclass
class _Context:
    """Arrays shared by the trackers: events of the chunk (bearings, sensor pixel, polarity; batch b's events
    start at b * batch_size), per-pixel references and per-event reference scratch, batch mid-times, pose history
    (map dtype for the kernels, float64 for the output), the mapper."""

    bearings: np.ndarray
    pix: np.ndarray
    pol: np.ndarray
    refs: dict  # per-pixel reference state (kernels/baselines/smt.new_reference_state), local batch indices
    ref_uv: np.ndarray
    ref_n: np.ndarray
    ref_src: np.ndarray
    mids: np.ndarray
    hist: np.ndarray
    hist64: np.ndarray
    mapper: GrayscaleMapper
    contrast: float  # C / map gain
    sigma: float  # measurement_sigma / map gain
    batch_size: int
    min_disp: float
    max_lat: float
    max_events: int
    position_var: float = 0.0  # map px^2 (SmtConfig.crossing_position_var)
    max_len: float = 10.0  # map px: longer segments restart without a measurement (SmtConfig.max_segment_px)

    def select(self, b0: int, b1: int, sel_R: np.ndarray) -> None:
        """References of batches b0..b1-1 under the selection poses sel_R (one per batch)."""
        m = self.mapper
        ks.select_references(self.hist, sel_R, b0, b1, self.batch_size, self.bearings, self.pix, self.pol, self.refs,
                             m.width, m.height, self.max_len, self.min_disp, self.max_lat,
                             self.ref_uv, self.ref_n, self.ref_src, self.max_events)

    def measure_args(self, b: int):
        e0, e1 = b * self.batch_size, min((b + 1) * self.batch_size, len(self.pol))
        return self.bearings[e0:e1], self.ref_uv[e0:e1], self.ref_n[e0:e1], self.pol[e0:e1]


class EkfTracker:
    """Error-state EKF on SO(3), constant-velocity (or random-walk) motion model, batched brightness-increment
    updates with state (or pose) references; a chunk of batches per kernel launch (kernels/baselines/smt.ekf_track)."""

    name = "ekf"

    def __init__(self, r0: np.ndarray, cfg: SmtConfig, rng: np.random.Generator, w0=None):
        self.cfg = cfg
        ca = cfg.motion_model == "constant_acceleration"
        cv = ca or cfg.motion_model == "constant_velocity"
        self.state_R = np.array(r0, np.float64).reshape(1, 3, 3).copy()
        self.state_w = np.zeros((1, 3))
        if cv and w0 is not None:
            self.state_w[0] = w0
        p = np.zeros((1, 9 if ca else 6, 9 if ca else 6))
        p[0, :3, :3] = np.eye(3) * np.radians(cfg.initial_std_deg) ** 2
        if cv:
            p[0, 3:6, 3:6] = np.eye(3) * cfg.initial_velocity_std ** 2
        self.state_a = np.zeros((1, 3)) if ca else None  # the bootstrap's acceleration is not known: 0 +- its std
        if ca:
            p[0, 6:, 6:] = np.eye(3) * cfg.initial_acceleration_std ** 2
        self.state_P = p
        self.velocity_reference = cv and (ca or cfg.reference == "velocity")
        if ca:
            self.q = (cfg.pose_noise_std, 0.0, cfg.acceleration_velocity_std)
        elif cv:
            self.q = (cfg.pose_noise_std, 0.0, cfg.angular_acceleration_std)
        else:
            self.q = (cfg.angular_velocity_std, cfg.min_step_std, 0.0)
        self.q_jerk = cfg.angular_jerk_std if ca else 0.0
        self.step_std = cfg.acceleration_step_std if ca else 0.0
        self.jerk_used = []  # jerk intensity of each call (per-batch steps; report)
        self.kappa_sums = np.zeros(2)  # innovation consistency statistic (kernels/baselines/smt.py): numerator, denominator

    def run(self, b0: int, b1: int, ctx: _Context) -> np.ndarray:
        """Track batches b0..b1-1; returns (b1 - b0, 7): valid, supported, agreeing measurements, pose std (deg),
        significant measurements, innovation-consistency numerator and denominator (summed into kappa_sums)."""
        c, m = self.cfg, ctx.mapper
        if self.step_std > 0 and b1 > b0:
            # a random-walk step of step_std per batch (module doc): the kernel's jerk intensity (per second) at
            # this call's mean batch duration
            dt = float(ctx.mids[b1 - 1] - ctx.mids[b0 - 1]) / (b1 - b0)
            self.q_jerk = self.step_std / math.sqrt(max(dt, 1e-7))
            self.jerk_used.append(self.q_jerk)
        diag = ks.ekf_track(ctx.hist, ctx.hist64, ctx.mids, b0, b1, ctx.batch_size, ctx.bearings, ctx.pix, ctx.pol,
                            ctx.refs, ctx.ref_uv, ctx.ref_n, m.gradient, m.covariance, m.updates, ctx.contrast,
                            ctx.sigma, ctx.max_len, ctx.min_disp, ctx.max_lat, c.huber, *self.q,
                            c.ekf_iterations, self.state_R, self.state_w, self.state_P, self.velocity_reference,
                            ctx.ref_src, ctx.max_events, self.state_a, self.q_jerk, ctx.position_var)
        diag[:, 3] = np.degrees(np.sqrt(np.maximum(diag[:, 3], 0.0)))
        self.kappa_sums += diag[:, 5:7].sum(0)
        return diag


class PfTracker:
    """Bootstrap particle filter on SO(3): random walk, per-event likelihoods, systematic resampling."""

    name = "pf"

    def __init__(self, r0: np.ndarray, cfg: SmtConfig, rng: np.random.Generator, w0=None):
        self.cfg = cfg
        self.rng = rng
        n = cfg.num_particles
        noise = rng.normal(scale=np.radians(cfg.initial_std_deg), size=(n, 3))
        self.particles = so3.exp(noise) @ np.asarray(r0, np.float64)
        self.logw = np.zeros(n)
        self.R = np.array(r0, np.float64)
        self.resamples = 0

    def step(self, dt: float, ctx: _Context, b: int) -> np.ndarray:
        """One batch: (valid, supported, agreeing measurements at the estimate, particle spread in deg, significant
        measurements)."""
        cfg, m = self.cfg, ctx.mapper
        n = len(self.particles)
        std = max(cfg.angular_velocity_std * dt, cfg.min_step_std)
        self.particles = so3.exp(self.rng.normal(scale=std, size=(n, 3))) @ self.particles
        ctx.select(b, b + 1, self.R[None])  # references under the previous estimate (the random-walk prediction)
        bear, uv, cnt, pol = ctx.measure_args(b)
        ll = ks.pf_loglik(self.particles, bear, uv, cnt, pol, m.gradient, m.covariance, m.updates, ctx.contrast,
                          ctx.sigma, cfg.pf_outlier_density, ctx.position_var)
        logw = self.logw + ll
        logw -= logw.max()
        w = np.exp(logw)
        w /= w.sum()
        self.R = _orthonormalize(weighted_mean_rotation(self.particles, w))
        d = so3.log(self.particles @ self.R.T)
        spread = float(np.degrees(np.sqrt(np.max(w @ (d * d)))))
        if 1.0 / np.sum(w * w) < cfg.pf_resample_ess * n:
            self.particles = self.particles[systematic_resample(w, self.rng)]
            self.logw = np.zeros(n)
            self.resamples += 1
        else:
            self.logw = np.log(np.maximum(w, 1e-300))
        acc = ks.ekf_accumulate(self.R, bear, uv, cnt, pol, m.gradient, m.covariance, m.updates, ctx.contrast,
                                ctx.sigma, cfg.huber, ctx.position_var)
        return np.array([acc[9], acc[10], acc[11], spread, acc[16]])

    def run(self, b0: int, b1: int, ctx: _Context) -> np.ndarray:
        diag = np.zeros((b1 - b0, 5))
        for b in range(b0, b1):
            diag[b - b0] = self.step(float(ctx.mids[b] - ctx.mids[b - 1]), ctx, b)
            ctx.hist64[b] = self.R
            ctx.hist[b] = self.R
        return diag


# ------------------------------------------------------------------------------------------------------------
# the pipeline
# ------------------------------------------------------------------------------------------------------------
def _bootstrap_trajectory(events: Events, imu, groundtruth: Trajectory | None, seconds: float):
    if imu is not None and len(getattr(imu, "t", ())) >= 2:
        r0 = groundtruth.at(imu.t[0])[0] if groundtruth is not None else None
        return dead_reckoning(imu.t, imu.gyro, r0), "imu"
    if groundtruth is not None:
        return groundtruth, "groundtruth"
    if seconds > 0:
        raise InputError("SMT needs IMU data or ground truth to bootstrap (or bootstrap_seconds=0)")
    return Trajectory(np.array([events.t[0]]), np.eye(3)[None]), "identity"


def _bootstrap_velocity(boot: Trajectory, t: float, span: float = 0.005) -> np.ndarray:
    """Camera-frame angular velocity of the bootstrap trajectory over its last ``span`` s before ``t``."""
    t0 = max(boot.t_start, t - span)
    if t <= t0:
        return np.zeros(3)
    r = boot.at(np.array([t0, t]))
    return so3.log(r[0].T @ r[1]) / (t - t0)


def _aligned_chunks(chunks: Iterable[Events], batch_size: int, bootstrap_seconds: float,
                    size: int) -> Iterator[Events]:
    """Re-cut time-ordered chunks at batch boundaries: the first piece holds every event of the bootstrap
    (t < t_0 + bootstrap_seconds, rounded up to whole batches) and one batch more, so that bootstrap, gain
    calibration and the start of tracking happen in one piece; the next ones ``size`` events (a multiple of the
    batch size), the last whatever remains."""
    size = max(size // batch_size, 1) * batch_size
    pending: list[Events] = []
    count, want, t_boot = 0, None, None
    for chunk in chunks:
        if not len(chunk):
            continue
        if t_boot is None:
            t_boot = float(chunk.t[0]) + bootstrap_seconds
        pending.append(chunk)
        count += len(chunk)
        while pending:
            if want is None:  # the bootstrap piece: complete once an event at or after t_boot has arrived
                if pending[-1].t[-1] < t_boot:
                    break
                buf = Events.concatenate(pending) if len(pending) > 1 else pending[0]
                pending = [buf]
                # whole batches up to t_boot, plus one: tracking (and the gain calibration on the bootstrap's
                # last batches) must start in this piece
                want = (-(-int(np.searchsorted(buf.t, t_boot, side="left")) // batch_size) + 1) * batch_size
            if count < want:
                break
            buf = Events.concatenate(pending) if len(pending) > 1 else pending[0]
            yield buf[:want]
            pending = [buf[want:]] if len(buf) > want else []
            count -= want
            want = size
    if pending:
        yield Events.concatenate(pending) if len(pending) > 1 else pending[0]


def _calibrate_gain(cfg: SmtConfig, ctx: _Context, contrast: float, b_first: int, b_end: int,
                    max_batches: int = 400) -> float:
    """Map gain k with p n C ~ k g . dp, from the bootstrap's last gain_calibration_seconds (known poses: local
    batches b_first..b_end-1 of the first chunk, references already selected in ``ctx``).

    The mapping EKFs fit g per map pixel by least squares over events of every displacement, each assigned to
    the pixel nearest its segment's midpoint; the tracker reads g bilinearly along its (longer) segments. The
    two differ by a few percent to 30 % depending on the texture (measured 1.05-1.35 on the simulated
    DAVIS240C / DVS128 sequences at 1024 x 512), and the tracker reads a wrong scale as extra or missing motion:
    a velocity bias that SMT's relative measurements integrate into drift. k = sum(n C) / sum(p z_hat) over
    mapped measurements (a ratio of sums, unbiased by zero-mean noise in z_hat), clipped to [0.5, 2]; C and
    sigma are divided by k.
    """
    mids = ctx.mids
    first = int(np.searchsorted(mids[:b_end], mids[b_end - 1] - cfg.gain_calibration_seconds, side="left"))
    batches = np.arange(max(first, b_first), b_end)
    if len(batches) > max_batches:
        batches = batches[np.linspace(0, len(batches) - 1, max_batches).astype(np.int64)]
    tot = np.zeros(ks.N_ACC)
    m = ctx.mapper
    for b in batches:
        bear, uv, cnt, pol = ctx.measure_args(b)
        tot += ks.ekf_accumulate(ctx.hist[b], bear, uv, cnt, pol, m.gradient, m.covariance, m.updates, contrast,
                                 cfg.measurement_sigma, cfg.huber)
    if tot[10] < 100 or tot[14] <= 0:
        return 1.0
    return float(np.clip(contrast * tot[15] / tot[14], 0.5, 2.0))


def _loss_reason(cfg: SmtConfig, std_deg: float, R_now, t_now: float, t_track0: float, window, sums) -> str:
    """Why tracking is lost now ("" if it is not): see the module doc. ``window`` holds (t, R, counts) of the
    batches of the last loss_window s, ``sums`` their counts (valid, supported, agreeing, significant
    measurements)."""
    if not np.all(np.isfinite(R_now)) or not np.isfinite(std_deg):
        return "divergence: non-finite state"
    if std_deg > cfg.loss_max_std_deg:
        return f"divergence: pose std {std_deg:.2f} deg"
    if t_now - t_track0 < cfg.loss_window:
        return ""
    t_first, R_first = window[0][0], window[0][1]
    span = t_now - t_first
    if span > 0.5 * cfg.loss_window:
        rate = float(so3.geodesic_angle(R_first, R_now)) / span
        if rate > cfg.loss_max_angular_velocity:
            return f"divergence: {rate:.1f} rad/s"
    if sums[0] >= cfg.loss_min_measurements:
        support = sums[1] / sums[0]
        if support < cfg.loss_min_support:
            return f"map support: {100 * support:.1f}% of measurements on mapped pixels"
        if sums[3] >= cfg.loss_min_measurements and sums[2] / sums[3] < cfg.loss_min_agreement:
            return f"likelihood collapse: polarity agreement {100 * sums[2] / sums[3]:.1f}%"
    return ""


def _warm_up(dtype, cfg: SmtConfig) -> float:
    """Compile the kernels a run uses before it is timed: the mapping kernels, the reference selection, the gain
    calibration's sums and the tracker's own (PF: the likelihood; EKF: the filter with its state size and kind of
    reference). Returns the seconds spent."""
    start = time.perf_counter()
    km.warm_up(dtype)
    grad = np.zeros((2, 4, 2), dtype)
    cov = np.ones((2, 4, 3), dtype)
    upd = np.zeros((2, 4), np.int32)
    b = np.array([[0.0, 0.0, 1.0]], dtype)
    hist = np.repeat(np.eye(3, dtype=dtype)[None], 2, axis=0)
    bb = np.repeat(b, 2, axis=0)
    pix, pol = np.zeros(2, np.int32), np.ones(2, np.int8)
    uv, cnt = np.zeros((2, 2), dtype), np.zeros(2, np.int32)
    ks.select_references(hist, hist[:1], 0, 1, 2, bb, pix, pol, ks.new_reference_state(1), 4, 2, 10.0, 0.0, 90.0, uv,
                         cnt)
    ks.ekf_accumulate(np.eye(3), b, uv[:1], cnt[:1], pol[:1], grad, cov, upd, 0.2, 0.1, 2.0)
    if cfg.tracker == "pf":
        ks.pf_loglik(np.eye(3)[None], b, uv[:1], cnt[:1], pol[:1], grad, cov, upd, 0.2, 0.1, 0.05)
        return time.perf_counter() - start
    acceleration = cfg.motion_model == "constant_acceleration"
    state_refs = cfg.motion_model != "random_walk" and (acceleration or cfg.reference == "velocity")
    ns = 9 if acceleration else 6
    ks.ekf_track(hist, hist.astype(np.float64), np.array([0.0, 1e-3]), 1, 2, 1, bb, pix, pol,
                 ks.new_reference_state(1), uv, cnt, grad, cov, upd, 0.2, 0.1, 10.0, 0.0, 90.0, 2.0, 1.0, 1e-4, 1.0, 1,
                 np.eye(3)[None].copy(), np.zeros((1, 3)), np.eye(ns)[None] * 1e-4, state_refs,
                 state_a=np.zeros((1, 3)) if acceleration else None, q_jerk=1.0)
    return time.perf_counter() - start


class _PoseStore:
    """Per sensor pixel reference state with GLOBAL batch ids (-1: none) and the poses those batches had: what
    the stream keeps between chunks (referenced batches and the last one), so memory does not grow with it."""

    def __init__(self, num_pixels: int):
        self.refs = ks.new_reference_state(num_pixels)
        self.ref_gid = self.refs["ref_b"].astype(np.int64)
        self.last_gid = self.refs["last_b"].astype(np.int64)
        self.ids = np.zeros(0, np.int64)  # sorted global batch ids kept (referenced + the last batch)
        self.R = np.zeros((0, 3, 3))
        self.t = np.zeros(0)

    def local_layout(self, chunk: Events, bs: int):
        """Local batch layout of a chunk: 0 = the previous chunk's last batch (dt of the first batch), 1..nbc =
        this chunk, then the stored poses of older batches that pixels still refer to. Returns (nbc, mids,
        hist64, refs in local ids)."""
        nbc = -(-len(chunk) // bs)
        k_old = len(self.ids)
        mids = np.empty(1 + nbc + k_old)
        mids[1:1 + nbc] = batch_mid_times(chunk.t, bs)
        mids[1 + nbc:] = self.t
        hist64 = np.zeros((1 + nbc + k_old, 3, 3))
        hist64[1 + nbc:] = self.R
        if k_old:
            mids[0], hist64[0] = self.t[-1], self.R[-1]
        else:
            mids[0], hist64[0] = mids[1], np.eye(3)

        def to_local(g):
            return np.where(g >= 0, 1 + nbc + np.searchsorted(self.ids, g), -1).astype(np.int32)

        refs = {"ref_b": to_local(self.ref_gid), "last_b": to_local(self.last_gid), "last_p": self.refs["last_p"],
                "count": self.refs["count"]}
        return nbc, mids, hist64, refs

    def keep(self, refs: dict, nbc: int, g0: int, hist64: np.ndarray, mids: np.ndarray) -> None:
        """Back to global batch ids after a chunk (its first batch is global g0); keep the poses that pixels will
        refer to, and the last batch."""
        def to_global(loc):
            out = np.full(len(loc), -1, np.int64)
            cur, old = (loc >= 1) & (loc <= nbc), loc > nbc
            out[cur] = g0 + loc[cur] - 1
            out[old] = self.ids[loc[old] - 1 - nbc]
            return out

        self.ref_gid, self.last_gid = to_global(refs["ref_b"]), to_global(refs["last_b"])
        ids = np.union1d(np.union1d(self.ref_gid[self.ref_gid >= 0], self.last_gid[self.last_gid >= 0]),
                         [g0 + nbc - 1])
        in_chunk = ids >= g0
        old_pos = np.searchsorted(self.ids, ids[~in_chunk])
        new_R = np.empty((len(ids), 3, 3))
        new_t = np.empty(len(ids))
        new_R[in_chunk], new_t[in_chunk] = hist64[1 + ids[in_chunk] - g0], mids[1 + ids[in_chunk] - g0]
        new_R[~in_chunk], new_t[~in_chunk] = self.R[old_pos], self.t[old_pos]
        self.ids, self.R, self.t = ids, new_R, new_t


class _MapFeeder:
    """Gives the mapper the tracked batches of a chunk, ``map_batches`` at a time, lagging the tracker."""

    def __init__(self, mapper: GrayscaleMapper, chunk: Events, ctx: _Context, map_batches: int):
        self.mapper, self.chunk, self.ctx, self.map_batches = mapper, chunk, ctx, map_batches
        self.mapped = 1  # local batches already given to the mapper

    def __call__(self, upto: int) -> None:
        bs, n, ctx = self.ctx.batch_size, len(self.chunk), self.ctx
        while self.mapped < upto:
            lo, hi = self.mapped, min(upto, self.mapped + self.map_batches)
            e0, e1 = (lo - 1) * bs, min((hi - 1) * bs, n)
            self.mapper.update(self.chunk[e0:e1], ctx.hist[lo:hi], bs, bearings=ctx.bearings[bs + e0:bs + e1],
                               batch_times=ctx.mids[lo:hi])
            self.mapped = hi


class _LossWatch:
    """The loss tests of the tracked batches (module doc): the window of the last loss_window s and, once
    lost, why and from when."""

    def __init__(self, cfg: SmtConfig):
        self.cfg = cfg
        self.window: deque = deque()
        self.sums = np.zeros(4)  # valid, supported, agreeing, significant measurements in the window
        self.totals = np.zeros(4)
        self.status, self.reason, self.lost_t, self.detected_at = "ok", "", None, None

    def batches(self, diag: np.ndarray, b0: int, b1: int, mids: np.ndarray, hist64: np.ndarray,
                t_track0: float) -> bool:
        """Loss checks of batches b0..b1-1 (diagnostics row b - b0), batch by batch; True when tracking is lost."""
        cfg = self.cfg
        for i, b in enumerate(range(b0, b1)):
            d = diag[i, [0, 1, 2, 4]]
            self.totals += d
            self.window.append((mids[b], hist64[b], d))
            self.sums += d
            while self.window and self.window[0][0] < mids[b] - cfg.loss_window:
                self.sums -= self.window.popleft()[2]
            why = _loss_reason(cfg, diag[i, 3], hist64[b], float(mids[b]), t_track0, self.window, self.sums)
            if why:
                self.lost(why, float(mids[b]), max(float(mids[b]) - cfg.loss_window, t_track0))
                return True
        return False

    def lost(self, reason: str, detected_at: float, lost_t: float) -> None:
        self.status, self.reason, self.detected_at, self.lost_t = "lost", reason, detected_at, lost_t


def _chunk_context(cfg: SmtConfig, chunk: Events, camera: Camera, mapper: GrayscaleMapper, refs: dict,
                   mids: np.ndarray, hist: np.ndarray, hist64: np.ndarray, contrast: float, sigma: float) -> _Context:
    """The trackers' arrays of a chunk; events are padded by one batch so that local batch b's events start at
    b * batch_size, as the kernels index them."""
    bs, n, dtype = (cfg.batch_size if cfg.tracker == "ekf" else cfg.pf_batch_size), len(chunk), mapper.dtype
    pad = lambda a: np.concatenate([np.zeros((bs,) + a.shape[1:], a.dtype), a])  # noqa: E731
    pix = np.ascontiguousarray(pad(km.sensor_index(chunk.x, chunk.y, camera.width)))
    bearings = np.ascontiguousarray(pad(camera.bearings(chunk.x, chunk.y, dtype=dtype)))
    pol = np.ascontiguousarray(pad(np.asarray(chunk.p, np.int8)))
    max_len = min(cfg.max_segment_px, cfg.mapping.outlier_distance_px) if cfg.tracker == "ekf" \
        else cfg.mapping.outlier_distance_px
    return _Context(bearings, pix, pol, refs, np.zeros((bs + n, 2), dtype), np.zeros(bs + n, np.int32),
                    np.zeros(bs + n, np.int32), mids, hist, hist64, mapper, contrast, sigma, bs,
                    cfg.min_displacement_px, cfg.max_latitude_deg, cfg.max_segment_events, cfg.crossing_position_var,
                    max_len)


def _consistency_check(cfg: SmtConfig, camera: Camera, chunk: Events, ctx: _Context, nbb: int,
                       t_track0: float) -> tuple[MotionConsistencyCheck, float]:
    """The motion consistency check from the start of tracking (after nbb bootstrap batches); its compile time."""
    checker = MotionConsistencyCheck(camera, t_track0, cfg.consistency_interval, cfg.consistency_span,
                                     cfg.consistency_min_ratio, cfg.consistency_checks,
                                     drift_horizon=cfg.consistency_drift_horizon,
                                     drift_parts=cfg.consistency_drift_parts, drift_min_deg=cfg.consistency_drift_deg)
    seconds = checker.compile()
    boot_events = int(nbb * ctx.batch_size)
    checker.update(chunk[max(boot_events - 1, 0):boot_events], ctx.mids[nbb:nbb + 1], ctx.hist64[nbb:nbb + 1],
                   t_track0)
    return checker, seconds


def _track_chunk(trk, ctx: _Context, chunk: Events, b_start: int, nbc: int, map_batches: int, watch: _LossWatch,
                 checker, feed_mapper: _MapFeeder, t_track0: float) -> int:
    """Track batches b_start..nbc of a chunk, map_batches per launch, with the loss tests after each launch; the
    mapper gets the tracked batches. Returns the end of the local batches kept (a lost track ends where its
    failing window started)."""
    bs, n, mids, hist64 = ctx.batch_size, len(chunk), ctx.mids, ctx.hist64
    end = 1 + nbc
    b0 = b_start
    while b0 <= nbc and watch.status == "ok":
        b1 = min(b0 + map_batches, 1 + nbc)
        watch.batches(trk.run(b0, b1, ctx), b0, b1, mids, hist64, t_track0)
        if watch.status == "ok" and checker is not None:
            e0, e1 = (b0 - 1) * bs, min((b1 - 1) * bs, n)
            failed_from = checker.update(chunk[e0:e1], mids[b0:b1], hist64[b0:b1], float(mids[b1 - 1]))
            if failed_from is not None:
                watch.lost(checker.failure, float(mids[b1 - 1]), max(failed_from, t_track0))
        if watch.status == "ok":
            feed_mapper(b1)
        else:
            end = b1
        b0 = b1
    if watch.status != "ok":  # map what was tracked before the failure (in this chunk)
        end = max(int(np.searchsorted(mids[1:end], watch.lost_t, side="right")) + 1, b_start)
        feed_mapper(end)
    return end


def _smt_report(cfg: SmtConfig, trk, checker, watch: _LossWatch, trajectory: Trajectory, gmap, figures: dict) -> dict:
    """report.json of an SMT run; ``figures``: counts, times and bootstrap facts gathered along the run."""
    wall, n_total, n_tracked, track_seconds = (figures.pop(k) for k in
                                               ("wall_seconds", "events_processed", "events_tracked",
                                                "tracking_seconds"))
    report = {
        "method": f"smt-{cfg.tracker}",
        "status": watch.status,
        "lost_at": float(trajectory.t_end) if watch.status == "lost" else None,
        "lost_detected_at": watch.detected_at,
        "lost_reason": watch.reason or None,
        "events_processed": int(n_total),
        "events_tracked": int(n_tracked),
        "bootstrap_source": figures["bootstrap_source"],
        "bootstrap_end": figures["bootstrap_end"],
        "contrast_threshold": figures["contrast_threshold"],
        "map_gain": figures["map_gain"],
        "wall_seconds": wall,
        "compile_seconds": figures["compile_seconds"],
        "tracking_seconds": track_seconds,
        "us_per_event": 1e6 * wall / max(n_total, 1),
        "tracking_us_per_event": 1e6 * track_seconds / max(n_tracked, 1),
        "consistency": checker.summary() if checker is not None else None,
        "measurements": {k: int(v) for k, v in zip(("valid", "supported", "agree", "significant"), watch.totals)},
        "map": gmap.summary(),
        "parameters": dataclasses.asdict(cfg),
    }
    if cfg.tracker == "pf" and trk is not None:
        report["resamples"] = int(trk.resamples)
    if isinstance(trk, EkfTracker) and trk.jerk_used:
        # the jerk intensity the per-batch acceleration steps came to (rad/s^2.5): min, median, max over the calls
        report["angular_jerk_std_range"] = [float(np.min(trk.jerk_used)), float(np.median(trk.jerk_used)),
                                            float(np.max(trk.jerk_used))]
    if isinstance(trk, EkfTracker) and trk.kappa_sums[1] > 0:
        # innovation consistency (kernels/baselines/smt.py): ~1 when the batch innovations match the filter's covariance
        report["innovation_kappa"] = float(trk.kappa_sums[0] / trk.kappa_sums[1])
    return report


def _trajectory(out_t: list, out_R: list, watch: _LossWatch) -> Trajectory:
    """The tracked poses (one per batch), cut where the failing window of a lost track started."""
    times, poses = np.concatenate(out_t), np.concatenate(out_R)
    if watch.status != "ok":
        keep_n = max(int(np.searchsorted(times, watch.lost_t, side="right")), 1)
        times, poses = times[:keep_n], poses[:keep_n]
    keep = np.concatenate([[True], np.diff(times) > 0])
    return Trajectory(times[keep], poses[keep])


def run_smt(events: Events | Iterable[Events], camera: Camera, config: SmtConfig | None = None,
            tracker: str | None = None, imu=None, groundtruth: Trajectory | None = None,
            contrast_threshold: float | None = None) -> SmtResult:
    """Run PF-SMT or EKF-SMT on time-ordered events (an Events, an iterable of chunks or a dataset).

    Streaming: events are processed in batch-aligned chunks of ``chunk_events`` (the first one spans the
    bootstrap); between chunks only per-pixel state is kept (the mapper's EKFs, the pose of each sensor pixel's
    last event), so memory does not grow with the input, except for the output trajectory (one pose per batch).
    ``tracker`` overrides ``config.tracker``. ``imu``: an object with t (N,) and gyro (N, 3) in the camera frame
    (ti_cmax.io.ImuData); ``groundtruth`` bootstraps when there is no IMU (and fixes the world frame of the IMU
    dead reckoning). ``contrast_threshold``: C (default: :func:`smt_contrast` without a dataset path, i.e.
    mapping.contrast_threshold or 0.22). Never raises on tracking failure: see ``report['status']``.
    """
    cfg = config or SmtConfig()
    if tracker is not None:
        cfg = dataclasses.replace(cfg, tracker=tracker)
    wall0 = time.perf_counter()
    contrast = float(contrast_threshold) if contrast_threshold else smt_contrast(cfg)
    mapper = GrayscaleMapper(camera, *cfg.mapping.pano_size, cfg.mapping, contrast)
    figures = {"compile_seconds": _warm_up(mapper.dtype, cfg),
               "contrast_threshold": contrast, "map_gain": 1.0, "bootstrap_end": None, "tracking_seconds": 0.0}
    bs = cfg.batch_size if cfg.tracker == "ekf" else cfg.pf_batch_size
    map_batches = max(1, cfg.map_update_events // bs)
    rng = np.random.default_rng(cfg.seed)
    store = _PoseStore(camera.width * camera.height)
    out_t, out_R = [], []  # output trajectory pieces (batch mid-times and poses)
    boot = trk = checker = t_boot = t_track0 = None
    c_eff, sigma_eff = contrast, cfg.measurement_sigma
    watch = _LossWatch(cfg)
    n_total = n_tracked = g0 = 0  # g0: global index of the chunk's first batch
    for chunk in _aligned_chunks(as_chunks(events), bs, cfg.bootstrap_seconds, cfg.chunk_events):
        n = len(chunk)
        if boot is None:
            boot, figures["bootstrap_source"] = _bootstrap_trajectory(chunk, imu, groundtruth, cfg.bootstrap_seconds)
            t_boot = float(chunk.t[0]) + cfg.bootstrap_seconds
        nbc, mids, hist64, refs = store.local_layout(chunk, bs)
        nbb = 0  # bootstrap batches: known poses
        if t_track0 is None:
            nbb = min(max(int(np.searchsorted(mids[1:1 + nbc], t_boot, side="left")), 1), nbc)
            hist64[1:1 + nbb] = boot.at(mids[1:1 + nbb])
        ctx = _chunk_context(cfg, chunk, camera, mapper, refs, mids, hist64.astype(mapper.dtype), hist64, c_eff,
                             sigma_eff)
        feed_mapper = _MapFeeder(mapper, chunk, ctx, map_batches)
        b_start = 1
        if t_track0 is None:
            feed_mapper(1 + nbb)
            ctx.select(1, 1 + nbb, ctx.hist[1:1 + nbb])
            b_start = 1 + nbb
            figures["bootstrap_end"] = float(mids[nbb])
            if b_start <= nbc:  # tracking starts in this chunk
                t_track0 = figures["bootstrap_end"]
                if cfg.gain_calibration_seconds > 0:
                    figures["map_gain"] = _calibrate_gain(cfg, ctx, contrast, 1, 1 + nbb)
                c_eff, sigma_eff = contrast / figures["map_gain"], cfg.measurement_sigma / figures["map_gain"]
                ctx.contrast, ctx.sigma = c_eff, sigma_eff
                trk = (EkfTracker if cfg.tracker == "ekf" else PfTracker)(hist64[nbb], cfg, rng,
                                                                          _bootstrap_velocity(boot, t_track0))
                if cfg.consistency_interval > 0:
                    checker, seconds = _consistency_check(cfg, camera, chunk, ctx, nbb, t_track0)
                    figures["compile_seconds"] += seconds
        tic = time.perf_counter()
        end = 1 + nbc  # local batches kept in the output
        if trk is not None:
            end = _track_chunk(trk, ctx, chunk, b_start, nbc, map_batches, watch, checker, feed_mapper, t_track0)
            n_tracked += min((end - 1) * bs, n) - (b_start - 1) * bs
        figures["tracking_seconds"] += time.perf_counter() - tic
        out_t.append(mids[1:end])
        out_R.append(hist64[1:end].copy())
        n_total += min((end - 1) * bs, n)
        if watch.status != "ok":
            break
        store.keep(refs, nbc, g0, hist64, mids)
        g0 += nbc
    if boot is None:
        raise InputError("SMT needs events, got none")
    gmap = mapper.reconstruct()
    trajectory = _trajectory(out_t, out_R, watch)
    figures.update(wall_seconds=time.perf_counter() - wall0 - figures["compile_seconds"], events_processed=n_total,
                   events_tracked=n_tracked)
    return SmtResult(trajectory, gmap, _smt_report(cfg, trk, checker, watch, trajectory, gmap, figures))


def run_smt_ekf(events, camera, config: SmtConfig | None = None, **kwargs) -> SmtResult:
    """EKF-SMT: :func:`run_smt` with tracker="ekf"."""
    return run_smt(events, camera, config, tracker="ekf", **kwargs)


def run_smt_pf(events, camera, config: SmtConfig | None = None, **kwargs) -> SmtResult:
    """PF-SMT: :func:`run_smt` with tracker="pf"."""
    return run_smt(events, camera, config, tracker="pf", **kwargs)


def _as_baseline(tracker: str, events_or_chunks, camera, config=None, imu=None, groundtruth=None,
                 contrast_threshold=None):
    """Registry adapter: (events, camera, BaselineConfig, imu) -> BaselineResult (map: the 8-bit grayscale
    panorama; report['us_per_event'] = {'frontend': ...} like the other baselines, the SMT figures kept apart).
    The SMT parameters come from ``config.smt`` when the BaselineConfig has that section, else the defaults."""
    cfg = getattr(config, "smt", None) or SmtConfig()
    res = run_smt(events_or_chunks, camera, cfg, tracker=tracker, imu=imu,
                  groundtruth=groundtruth, contrast_threshold=contrast_threshold)
    report = dict(res.report)
    report["smt_us_per_event"] = report["us_per_event"]
    report["us_per_event"] = {"frontend": report["smt_us_per_event"]}
    report["map_image"] = "8-bit grayscale panorama (Poisson-integrated log intensity)"
    return BaselineResult(res.trajectory, res.map.to_uint8(cfg.mapping.display_percentile_low,
                                                          cfg.mapping.display_percentile_high), report,
                          map_kind="intensity")  # drawn as is: the event-map renderer inverts (more events = darker)


def smt_ekf_baseline(events_or_chunks, camera, config=None, imu=None, **kwargs):
    """Registry entry "smt-ekf" (BASELINES signature)."""
    return _as_baseline("ekf", events_or_chunks, camera, config, imu, **kwargs)


def smt_pf_baseline(events_or_chunks, camera, config=None, imu=None, **kwargs):
    """Registry entry "smt-pf" (BASELINES signature)."""
    return _as_baseline("pf", events_or_chunks, camera, config, imu, **kwargs)


__all__ = ["SmtConfig", "SmtResult", "run_smt", "run_smt_ekf", "run_smt_pf", "smt_ekf_baseline", "smt_pf_baseline",
           "smt_contrast", "TRACKERS",
           "EkfTracker", "PfTracker", "systematic_resample", "weighted_mean_rotation"]
