"""CMax-GAE baseline (Kim & Kim, RA-L 2021): contrast maximization over globally aligned events.

Events are cut into intervals of ``gae_interval`` (25 ms: poses at 40 Hz, at the interval mid-times t_ref) and
kept 1 of ``gae_event_sample_rate`` (4, as the original), but never fewer than ``gae_min_sampled_events`` per
interval: 1 of q with q = min(Q, n // min), at least 1. The original's 1 of 4 suits DAVIS240C-like rates (60-80 k
events per interval on the benchmark); on the 0.7 M events/s DVS128 playroom-like sequence it leaves 4.4 k events
per interval and the tracker drifts away (17.0 deg RMSE; 5.3 deg keeping 1 of 2, 0.45 deg keeping all).
For each interval, with R the pose at the previous t_ref:
1. I_G: the past events (a fixed-size equirectangular histogram of world bearings on the unit sphere,
   ``gae_sphere_height`` x 2 ``gae_sphere_height`` cells) splatted into a view twice as wide and high as the sensor
   around R, blurred by ``gae_blur_sigma`` (G);
2. (omega, phi) maximize C = mean_px (I_L(omega, exp(phi)) + G)^2 (Eq. 6, ``kernels.gae``) by RMSProp
   (``gae_iterations`` 65, step ``gae_step`` 0.05, squared-gradient decay ``gae_decay`` 0.995, from the public code)
   started from the previous omega and the constant-velocity increment; the parameters are optimized in pixel
   units (omega f dT / 2 and phi f, f the focal length), so the step means the same for every sensor; the
   squared-gradient average starts at the first squared gradient (see ``rmsprop_maximize``);
3. R <- R exp(phi) (Eq. 7); the interval's events are added to the sphere at their warped world bearings.
The first interval only estimates omega (nothing to align to) and defines the world frame (R = I). Intervals with
fewer than ``gae_min_events`` sampled events (camera about still) keep the constant-velocity pose unoptimized.

Memory is bounded (the paper notes the original keeps every past event): the input is streamed interval by
interval, and the sphere histogram has a fixed size whatever the sequence length, at the price of quantizing past
bearings to cells (0.18 deg at the default 1024 rows).
"""
from __future__ import annotations

import time
from dataclasses import asdict, dataclass

import numpy as np

from ti_cmax.kernels.baselines import gae as G
from ti_cmax.kernels.baselines.rtpt import footprint_bbox, view_border_rays
from ti_cmax.kernels.pano import vote_map

from ti_cmax.pipelines.frontend import time_intervals
from .result import AngularVelocity, BaselineResult, CountedChunks
from scipy.ndimage import gaussian_filter

from ti_cmax import so3
from ti_cmax.config import Params, param
from ti_cmax.errors import InputError
from ti_cmax.progress import progress
from ti_cmax.trajectory import Trajectory


@dataclass(frozen=True)
class GAEConfig(Params):
    """CMax-GAE (Kim & Kim 2021): defaults of the public code where it has them."""

    gae_interval: float = param(0.025, "time per estimate (40 Hz)", unit="s", gt=0)
    gae_event_sample_rate: int = param(4, "keep 1 of Q events (original: 4) ...", ge=1)
    gae_min_sampled_events: int = param(15000, "... unless an interval would keep fewer than this", unit="events",
                                        ge=1, zero="always 1 of Q")
    gae_iterations: int = param(65, "RMSProp iterations", ge=0)
    gae_step: float = param(0.05, "RMSProp step", unit="px", gt=0)
    gae_decay: float = param(0.995, "RMSProp decay of the squared-gradient average", gt=0, lt=1)
    gae_blur_sigma: float = param(1.0, "Gaussian blur of the global view I_G (0: none)", unit="px", ge=0)
    gae_sphere_height: int = param(1024, "rows of the sphere histogram (columns = 2 x rows)", unit="px", ge=8)
    gae_min_events: int = param(200, "an interval with fewer (sampled) events keeps the pose", unit="events", ge=0)


class SphereMap:
    """Fixed-size memory of past events: bilinear votes of world bearings into an equirectangular histogram."""

    def __init__(self, height: int):
        self.height, self.width = int(height), 2 * int(height)
        self.hist = np.zeros((self.height, self.width), np.float32)
        self.events = 0

    def add(self, bearings: np.ndarray, rotations: np.ndarray) -> None:
        if len(bearings):
            vote_map(bearings, rotations, self.width, self.height, out=self.hist)
            self.events += len(bearings)

    @property
    def nbytes(self) -> int:
        return int(self.hist.nbytes)


def sample_step(n: int, cfg: GAEConfig) -> int:
    """Keep 1 of this many of an interval's n events (see the module docstring)."""
    if cfg.gae_min_sampled_events <= 0:
        return cfg.gae_event_sample_rate
    return max(1, min(cfg.gae_event_sample_rate, n // cfg.gae_min_sampled_events))


def rmsprop_maximize(fun, x0, iterations, step, decay, mask=None, eps=1e-12):
    """RMSProp ascent: v <- d v + (1 - d) g^2, x <- x + step g / (sqrt(v) + eps); returns (x, last cost).

    v starts at the first squared gradient (not 0): the first steps are then ``step`` long, not up to
    step / sqrt(1 - d) = 14 step, which on the nearly flat objectives of slow motion kicks the pose away."""
    x = np.array(x0, dtype=np.float64)
    v = None
    cost = None
    for _ in range(iterations):
        cost, g = fun(x)
        if mask is not None:
            g = g * mask
        v = g * g if v is None else decay * v + (1 - decay) * g * g
        x = x + step * g / (np.sqrt(v) + eps)
    return x, cost


def _compile(camera) -> float:
    tic = time.perf_counter()
    kv = G.view_K(camera.K, 4, 4)
    obj = G.GAEObjective(kv, 8, 8)
    obj.set_interval(np.array([[0.0, 0.0, 1.0]]), np.zeros(1))
    obj.evaluate(np.zeros(3), np.zeros(3))
    G.render_sphere(np.zeros((8, 16), np.float32), np.eye(3), kv, 8, 8, (0, 8, 0, 16))
    SphereMap(8).add(np.array([[0.0, 0.0, 1.0]], np.float32), np.eye(3)[None])
    return time.perf_counter() - tic


def _gae_result(cfg: GAEConfig, chunks: CountedChunks, times: list, rots: list, omegas: list, used: int, obj,
                sphere: SphereMap, wall0: float, tic: float, compile_s: float):
    """BaselineResult of a run: the poses and angular velocities at the interval mid-times, the sphere histogram
    and the report (wall0 / tic: start of the run / of the tracking)."""
    if len(times) < 2:
        raise InputError(f"CMax-GAE needs at least 2 intervals with {cfg.gae_min_events} sampled events")
    seconds = time.perf_counter() - tic
    n_read = chunks.count
    report = {
        "status": "ok",
        "method": "cmax-gae",
        "events_processed": int(n_read),
        "events_used": int(used),
        "intervals": int(len(times)),
        "evaluations": int(obj.evaluations),
        "sphere_bytes": sphere.nbytes,
        "wall_seconds": time.perf_counter() - wall0,
        "compile_seconds": compile_s,
        "us_per_event": {"frontend": seconds * 1e6 / max(n_read, 1)},
        "parameters": asdict(cfg),
    }
    times = np.asarray(times)
    return BaselineResult(Trajectory(times, np.asarray(rots)), sphere.hist, report,
                          AngularVelocity(times, np.asarray(omegas)))


def run_cmax_gae(events_or_chunks, camera, config=None, imu=None):
    """CMax-GAE on events (Events, chunks or a dataset, streamed) -> BaselineResult (40 Hz trajectory, sphere
    histogram)."""
    cfg = config.gae if config is not None else GAEConfig()
    wall0 = time.perf_counter()
    chunks = CountedChunks(events_or_chunks)
    T = float(cfg.gae_interval)
    intervals = time_intervals(chunks, T)
    compile_s = _compile(camera)
    tic = time.perf_counter()
    vw, vh = 2 * camera.width, 2 * camera.height
    kv = G.view_K(camera.K, camera.width, camera.height)
    rays = view_border_rays(kv, vw, vh)
    obj = G.GAEObjective(kv, vw, vh)
    sphere = SphereMap(cfg.gae_sphere_height)
    f = 0.5 * (camera.fx + camera.fy)
    scale = np.array([f * T / 2] * 3 + [f] * 3)
    R = np.eye(3)
    omega = np.zeros(3)
    t_prev = None
    times, rots, omegas = [], [], []
    used = 0
    bar = progress(total=chunks.span, desc="cmax-gae", unit="s")
    try:
        for _, t_start, sub in intervals:  # streamed: memory holds one input chunk and one interval
            t_ref = t_start + 0.5 * T
            first = t_prev is None
            sub = sub[::sample_step(len(sub), cfg)]
            used += len(sub)
            if len(sub) >= cfg.gae_min_events:
                b = camera.bearings(sub.x, sub.y)
                dts = sub.t - t_ref
                g_img = None
                if not first and sphere.events:
                    bbox = footprint_bbox(R, rays, sphere.width, sphere.height)
                    g_img = G.render_sphere(sphere.hist, R, kv, vw, vh, bbox)
                    if cfg.gae_blur_sigma > 0:
                        g_img = gaussian_filter(g_img, cfg.gae_blur_sigma, mode="constant")
                obj.set_interval(b, dts, g_img)
                phi0 = np.zeros(3) if first else omega * (t_ref - t_prev)
                x0 = np.concatenate([omega, phi0]) * scale

                def fun(x):
                    c, g = obj.evaluate(x[:3] / scale[:3], x[3:] / scale[3:])
                    return c, g / scale

                mask = np.array([1.0] * 3 + [0.0 if first else 1.0] * 3)
                x, _ = rmsprop_maximize(fun, x0, cfg.gae_iterations, cfg.gae_step, cfg.gae_decay, mask)
                omega = x[:3] / scale[:3]
                R = R @ so3.exp(x[3:] / scale[3:])
                sphere.add(b, R @ so3.exp(omega[None] * dts[:, None]))
            elif not first:
                R = R @ so3.exp(omega * (t_ref - t_prev))
            else:
                continue
            times.append(t_ref)
            rots.append(R)
            omegas.append(omega)
            if t_prev is not None:
                bar.update(t_ref - t_prev)
            t_prev = t_ref
        bar.done()  # the stage has ended: its bar at 100 %
    finally:
        bar.close()
    return _gae_result(cfg, chunks, times, rots, omegas, used, obj, sphere, wall0, tic, compile_s)
