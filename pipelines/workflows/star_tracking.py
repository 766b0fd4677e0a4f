"""Star tracking (paper Sec. V): front-end over the whole sequence, then offline BA from its integrated
trajectory, evaluated by the angle between relative rotations over 400 ms (Chin et al.'s benchmark, Tab. VIII).

Data: the star dataset's form (``ti_cmax.io.star``: float undistorted events + 3x3 calibration) or any
dataset ``open_dataset`` reads. :func:`simulate_star_sequence` makes a Chin-like sequence (DAVIS240C, star
field rotating at a constant 4 deg/s) in either form.

Star-tracking defaults (:data:`STAR_DEFAULTS`, applied under the user's ``--set``/``--config`` values): star
fields are sparse and slow (4 deg/s is ~14 px/s on a DAVIS240C: 1.4 px in the front-end's default 0.1 s
window), so
* the front-end uses longer packets: a packet holds at least every event within t_ref +- 0.25 s
  (``frontend_min_packet_span=0.5``, ``still_span_factor=60`` so it is never shrunk below that) and the
  event-rate floor is lowered to 1000 ev/s: about 7 px of motion per packet, enough to measure omega;
* the back-end windows are 0.4 s (stride 0.2 s) with the event-rate floor at 1000 ev/s (the global default
  10 000 ev/s would skip BA on the sparsest real sequences, 1.4 M events over 45 s = 31 k ev/s, and on any
  fainter field). The map follows the sensor rule (``sensor_defaults``: 2048x1024 on a DAVIS240C); it was fixed
  at that size, which a longer focal length or a larger sensor would have sampled coarser than its pixels.

These settings are for slow rotations: a run whose camera turns faster than STAR_MAX_RATE_DEG (as the front-end or a
probe of short packets measures it) gets a warning in report.json ("warnings") and on the command line.
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Iterable

import numpy as np

from ti_cmax.camera import Camera
from ti_cmax.config import SlamConfig, build_config, config_to_dict, load_config, parse_overrides, update_config
from ti_cmax.errors import InputError
from ti_cmax.events import Events
from ti_cmax.io import open_dataset_from_config
from ti_cmax.io.star import is_star_dataset, open_star_dataset, undistorted_star_events, write_star_dataset
from ti_cmax.metrics import STAR_WINDOW, star_tracking_errors
from ti_cmax.pipelines.frontend import FrontendResult, estimate_angular_velocity
from ti_cmax.pipelines.slam import SlamResult, refine
from ti_cmax.simulate import SimulatorConfig, simulate_sequence, simulate_to_folder
from ti_cmax.trajectory import Trajectory

STAR_DEFAULTS: dict = {
    "frontend_min_packet_span": 0.5,
    "still_span_factor": 60.0,
    "frontend_min_event_rate": 1000.0,
    "backend_time_window_size": 0.4,
    "backend_sliding_window_stride": 0.2,
    "backend_min_ev_rate": 1000.0,
}


# The motion star tracking is made for: a slow rotation (the half-second packets above hold one omega each). Measured
# on simulated 3 s DAVIS240C star fields (1000 stars, random motion): the BA's 400 ms error was 0.04-0.12 deg for
# peaks of 11-57 deg/s, 0.27 deg at 115 deg/s and 61 deg at 286 deg/s, every packet then taken for still; constant
# rotations track up to 120 deg/s (0.11 deg). Faster motion gets a warning (report.json "warnings"): use slam.
STAR_MAX_RATE_DEG = 60.0
# the front-end's omega alone cannot tell: beyond its range it reads omega = 0. A probe runs the global front-end
# (40 ms packets) on PROBE_SPAN s of events at up to PROBE_COUNT times spread over the recording (~0.1 s of work)
PROBE_SPAN = 0.05
PROBE_COUNT = 8


class MotionProbe:
    """Passes event chunks through unchanged and keeps PROBE_SPAN s of events at PROBE_COUNT times spread over
    [t_start, t_end] (unknown range: every 0.5 s from the first event); :meth:`rates` measures |omega| there."""

    def __init__(self, t_range: tuple[float, float] | None):
        self.t_range = t_range
        self.samples: list[Events] = []
        self._next: float | None = None
        self._step = 0.5

    def __call__(self, chunks: Iterable[Events]) -> Iterable[Events]:
        for ev in chunks:
            if len(ev) and len(self.samples) < PROBE_COUNT:
                self._keep(ev)
            yield ev

    def _keep(self, ev: Events) -> None:
        if self._next is None:
            t0, t1 = self.t_range if self.t_range is not None else (float(ev.t[0]), None)
            if t1 is not None:
                self._step = max((t1 - t0 - PROBE_SPAN) / PROBE_COUNT, PROBE_SPAN)
            self._next = t0 + 0.5 * self._step
        while len(self.samples) < PROBE_COUNT and self._next <= ev.t[-1]:
            part = ev.slice_time(self._next, self._next + PROBE_SPAN)
            if len(part) > 1:
                self.samples.append(part)
            self._next += self._step

    def rates(self, camera: Camera) -> list[float]:
        """Median |omega| (deg/s) the global front-end measures in each sample."""
        from ti_cmax.pipelines.sensor_defaults import resolve_config

        cfg = resolve_config(SlamConfig(), camera).frontend
        out = []
        for ev in self.samples:
            fe = estimate_angular_velocity(ev, camera, cfg)
            if len(fe):
                out.append(float(np.degrees(np.median(np.linalg.norm(fe.omega, axis=1)))))
        return out


def motion_warning(omega: np.ndarray, probe_rates: list[float], limit_deg: float = STAR_MAX_RATE_DEG):
    """(figures, warning or None): the camera's rate as the star front-end's ``omega`` (M, 3) rad/s (95th
    percentile) and the probe (largest) measured it, and a warning when either is beyond ``limit_deg`` (naming the
    probe's rate when it is beyond)."""
    rates = np.degrees(np.linalg.norm(np.asarray(omega, dtype=float).reshape(-1, 3), axis=1))
    fe_rate = float(np.percentile(rates, 95)) if len(rates) else 0.0
    probe = max(probe_rates, default=0.0)
    figures = {"frontend_p95_deg_per_s": fe_rate, "probe_max_deg_per_s": probe, "design_max_deg_per_s": limit_deg}
    if max(fe_rate, probe) <= limit_deg:
        return figures, None
    rate = probe if probe > limit_deg else fe_rate  # the probe's short packets measure fast motion; the star
    # front-end's omega beyond its range is noise (thousands of deg/s on a 270 deg/s field)
    return figures, (f"the camera turns at up to {rate:.0f} deg/s, beyond the {limit_deg:g} deg/s star tracking is "
                     "made for (slow rotations: half-second packets with one omega each); its result is not to be "
                     "trusted: use ti-cmax slam for this motion")


def star_tracking_config(config_path=None, overrides=None) -> SlamConfig:
    """Global defaults <- STAR_DEFAULTS <- YAML file <- overrides (the user's values always win)."""
    import yaml

    values = dict(STAR_DEFAULTS)
    if config_path:
        load_config(SlamConfig, config_path)  # validates the file (InputError naming file and field)
        with open(config_path) as fh:
            values.update(_flat(yaml.safe_load(fh) or {}))
    cfg = build_config(SlamConfig, values, source=str(config_path or "star-tracking defaults"))
    ov = overrides if isinstance(overrides, dict) else parse_overrides(overrides)
    return update_config(cfg, ov, source="--set") if ov else cfg


def _flat(d: dict, prefix: str = "") -> dict:
    out = {}
    for k, v in d.items():
        if isinstance(v, dict):
            out.update(_flat(v, f"{prefix}{k}."))
        else:
            out[f"{prefix}{k}"] = v
    return out


@dataclass
class StarTrackingResult:
    frontend: FrontendResult
    frontend_trajectory: Trajectory  # integrated front-end omega
    ba: SlamResult  # offline BA (refine) from the front-end trajectory
    errors: dict | None  # {"frontend": {...}, "ba": {...}} relative-rotation errors when GT is given
    report: dict

    @property
    def trajectory(self) -> Trajectory:
        return self.ba.trajectory

    @property
    def map(self) -> np.ndarray:
        return self.ba.map


def _chunks(source, chunk_size: int) -> Iterable[Events]:
    if isinstance(source, Events):
        return [source]
    if callable(source):
        return source()
    if hasattr(source, "iter_events"):
        return source.iter_events(chunk_size)
    raise InputError("star tracking needs Events, a dataset or a callable returning event chunks "
                     "(the events are read twice: front-end, then BA)")


def _time_range(source) -> tuple[float, float] | None:
    """The time range of Events or of a dataset (None for a callable source)."""
    if isinstance(source, Events):
        return (float(source.t[0]), float(source.t[-1])) if len(source) else None
    if hasattr(source, "time_range"):
        return tuple(float(v) for v in source.time_range())
    return None


def relative_errors(groundtruth: Trajectory, estimate: Trajectory, window: float = STAR_WINDOW) -> dict:
    """Tab. VIII figures (deg) of one estimate: RMSE and std of the 400 ms relative-rotation error."""
    e = star_tracking_errors(groundtruth, estimate, window)
    return {"rmse_deg": e.rmse_deg, "std_deg": e.std_deg, "mean_deg": e.mean_deg, "count": e.count,
            "window_s": e.window}


def run_star_tracking(source, camera: Camera, config: SlamConfig | None = None, *,
                      groundtruth: Trajectory | None = None, window: float = STAR_WINDOW,
                      progress_total: float | None = None) -> StarTrackingResult:
    """Front-end over the whole sequence, then offline BA initialized from its integrated trajectory.

    ``source``: ``Events``, a dataset (``iter_events``) or a callable returning an iterable of chunks; it is
    read twice. ``config`` defaults to :func:`star_tracking_config` (star-tracking defaults).
    """
    cfg = config or star_tracking_config()
    wall0 = time.perf_counter()
    probe = MotionProbe(_time_range(source))
    fe = estimate_angular_velocity(probe(_chunks(source, cfg.dataset.chunk_size)), camera, cfg.frontend,
                                   progress_total=progress_total)
    if len(fe) < 2:
        raise InputError("too few events for star tracking: the front-end produced fewer than 2 packets")
    motion, warning = motion_warning(fe.omega, probe.rates(camera))
    fe_traj = fe.trajectory()
    ba = refine(_chunks(source, cfg.dataset.chunk_size), camera, fe_traj, cfg, progress_total=progress_total)
    errors = None
    if groundtruth is not None:
        errors = {"frontend": relative_errors(groundtruth, fe_traj, window),
                  "ba": relative_errors(groundtruth, ba.trajectory, window)}
    report = {
        "status": "ok",
        "method": "cmax-star-tracking (front-end + offline BA)",
        "events_processed": int(fe.timing.get("events_processed", 0)),
        "wall_seconds": time.perf_counter() - wall0,
        "us_per_event": {"frontend": fe.timing.get("us_per_event", 0.0),
                         "backend": ba.report["us_per_event"]["backend"]},
        "frontend": fe.summary(),
        "backend": ba.report["backend"],
        "hot_pixels": fe.hot_pixels,
        "star_defaults": dict(STAR_DEFAULTS),
        "motion": motion,
        "warnings": [warning] if warning else [],
        "parameters": config_to_dict(cfg),
    }
    if errors is not None:
        report["relative_rotation_error"] = errors
        report["rmse_deg"] = errors["ba"]["rmse_deg"]
        report["std_deg"] = errors["ba"]["std_deg"]
    return StarTrackingResult(fe, fe_traj, ba, errors, report)


# ------------------------------------------------------------------------------------------------
# simulated Chin-like sequences
# ------------------------------------------------------------------------------------------------

def star_simulator_config(duration: float = 30.0, *, num_stars: int = 1000, rate_deg: float = 4.0,
                          seed: int = 0, **overrides):
    """Simulator settings for a Chin-like sequence: DAVIS240C, star field, constant rotation (4 deg/s).

    1000 stars give about 60 k events/s, i.e. 1.4-2.8 M events over 20-45 s (the real sequences:
    1.4-6.2 M over 45 s)."""
    return SimulatorConfig(scene="stars", trajectory="constant", constant_rate_deg=rate_deg, duration=duration,
                           num_stars=num_stars, sensor="DAVIS240C", seed=seed, **overrides)


def simulate_star_sequence(out_dir, duration: float = 30.0, *, form: str = "star", num_stars: int = 1000,
                           rate_deg: float = 4.0, seed: int = 0, show_progress: bool = False, **overrides) -> dict:
    """Simulate a Chin-like sequence into ``out_dir``.

    form="star": the star dataset's form (events undistorted to float coordinates with the camera's K,
    calibration.txt = K^-1, groundtruth.txt); form="ecd": the simulator's ECD-layout folder. Returns the
    simulation info. The whole sequence is simulated in memory (45 s is ~3 M events, ~60 MB)."""
    cfg = star_simulator_config(duration, num_stars=num_stars, rate_deg=rate_deg, seed=seed, **overrides)
    if form == "ecd":
        return simulate_to_folder(cfg, out_dir, show_progress=show_progress)
    if form != "star":
        raise InputError(f"form must be 'star' or 'ecd', got {form!r}")
    seq = simulate_sequence(cfg, show_progress=show_progress)
    ev = undistorted_star_events(seq.events, seq.camera)
    write_star_dataset(out_dir, ev, np.linalg.inv(seq.camera.K), seq.groundtruth,
                       sensor_size=(seq.camera.width, seq.camera.height))
    return seq.info


def open_star_or_dataset(path, dataset_config):
    """The star dataset's form when recognized (``is_star_dataset``), else ``open_dataset_from_config``."""
    if is_star_dataset(path):
        return open_star_dataset(path, dataset_config.width or None, dataset_config.height or None)
    return open_dataset_from_config(path, dataset_config)


__all__ = ["STAR_DEFAULTS", "STAR_MAX_RATE_DEG", "MotionProbe", "motion_warning", "star_tracking_config", "StarTrackingResult", "run_star_tracking", "relative_errors",
           "star_simulator_config", "simulate_star_sequence", "open_star_or_dataset"]
