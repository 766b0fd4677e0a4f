"""Simulated sequences: in memory (:func:`simulate_sequence`) or streamed to an ECD-layout folder
(:func:`simulate_to_folder`); :func:`write_sequence` writes an in-memory sequence.

Folder contents: events.txt, events.h5, calib.txt, groundtruth.txt (TUM, gt_rate), imu.txt (imu_rate),
groundtruth_angular_velocity.txt (t wx wy wz, camera frame, gt_rate), panorama.png (the scene's
intensity, 8 bit) and simulation.json (all parameters, seed, gyro bias, event count and rate).
"""
from __future__ import annotations

import contextlib
import dataclasses
import json
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..camera import Camera
from ..errors import InputError
from ..events import Events
from ..outputs import OutputDir
from ..progress import progress
from ..trajectory import Trajectory
from .config import SimulatorConfig
from .generate import generate_events, pixel_speed_factor, render_times, sensor_camera
from .imu import simulate_imu
from .scenes import log_panorama, make_panorama
from .trajectories import RotationalMotion, make_motion, sample_times


@dataclass(frozen=True, eq=False)
class SimulatedSequence:
    events: Events
    camera: Camera
    groundtruth: Trajectory  # R_world_from_camera at gt_rate
    omega_t: np.ndarray  # (M,) times of the ground-truth angular velocity
    omega: np.ndarray  # (M, 3) rad/s, camera frame
    imu: "object"  # ti_cmax.io.ImuData (t, acc, gyro)
    panorama: np.ndarray  # (h, 2h) intensity in [0, 1] (anti-aliased), world frame
    gyro_bias: np.ndarray  # (3,) rad/s added to the gyro
    motion: RotationalMotion  # analytic omega(t) and exact R(t)
    config: SimulatorConfig
    info: dict


@dataclass(frozen=True, eq=False)
class _Setup:
    camera: Camera
    panorama: np.ndarray
    log_pano: np.ndarray
    motion: RotationalMotion
    times: np.ndarray
    imu: object
    gyro_bias: np.ndarray


def _as_config(config: SimulatorConfig | None, overrides: dict) -> SimulatorConfig:
    config = config or SimulatorConfig()
    return (dataclasses.replace(config, **overrides) if overrides else config).resolved()


def _setup(config: SimulatorConfig) -> _Setup:
    from ..io import ImuData

    camera = sensor_camera(config.sensor)
    pano = make_panorama(config, 1.0 / max(camera.fx, camera.fy))
    motion = make_motion(config.trajectory, config.duration, seed=config.seed,
                         max_angular_velocity=config.max_angular_velocity,
                         frequency_max=config.random_frequency_max, ramp_start=config.random_ramp_start,
                         constant_rate_deg=config.constant_rate_deg,
                         axis=config.rotation_axis, integration_rate=config.integration_rate,
                         turns=config.turns, wobble=config.pan_wobble)
    times = render_times(motion, camera, config.max_pixel_step, config.max_render_dt)
    t, acc, gyro, bias = simulate_imu(motion, config.imu_rate, gyro_bias_std=config.gyro_bias_std,
                                      gyro_noise_std=config.gyro_noise_std, acc_noise_std=config.acc_noise_std,
                                      gravity=config.gravity, seed=config.seed)
    return _Setup(camera, pano, log_panorama(pano, config.log_eps), motion, times, ImuData(t, acc, gyro), bias)


def _info(config: SimulatorConfig, s: _Setup, num_events: int, wall: float) -> dict:
    return {
        "config": dataclasses.asdict(config),
        "seed": config.seed,
        "camera": s.camera.to_dict(),
        "gyro_bias": s.gyro_bias.tolist(),
        "num_events": int(num_events),
        "event_rate": num_events / config.duration,
        "duration": config.duration,
        "num_renders": int(len(s.times)),
        "pixel_speed_factor": pixel_speed_factor(s.camera),
        "panorama_size": [int(s.panorama.shape[1]), int(s.panorama.shape[0])],
        "trajectory": {"kind": s.motion.kind, "params": s.motion.params,
                       "peak_angular_velocity": s.motion.max_speed(0, config.duration, 4000)},
        "wall_seconds": wall,
        "conventions": "R_world_from_camera; omega and gyro in the camera frame; gravity along world +y",
    }


def _progress(config: SimulatorConfig, show: bool):
    bar = progress(total=round(config.duration, 6), desc="simulate", unit="s") if show else None

    def update(t_end: float):
        if bar is not None:
            bar.n = round(t_end, 6)
            bar.refresh()

    return bar, update


def simulate_sequence(config: SimulatorConfig | None = None, *, show_progress: bool = False,
                      **overrides) -> SimulatedSequence:
    """Simulate a whole sequence in memory (tests, benchmarks). Keyword overrides replace config fields."""
    config = _as_config(config, overrides)
    start = time.perf_counter()
    s = _setup(config)
    bar, update = _progress(config, show_progress)
    try:
        events = Events.concatenate(list(generate_events(s.motion, s.camera, s.log_pano, config, s.times, update)))
    finally:
        if bar is not None:
            bar.close()
    gt_t = sample_times(config.duration, config.gt_rate)
    info = _info(config, s, len(events), time.perf_counter() - start)
    return SimulatedSequence(events, s.camera, s.motion.trajectory(config.gt_rate), gt_t, s.motion.omega(gt_t),
                             s.imu, s.panorama, s.gyro_bias, s.motion, config, info)


def _write_static(out: Path, config: SimulatorConfig, camera, motion: RotationalMotion, imu, panorama) -> None:
    import imageio.v3 as iio

    from ..io import write_angular_velocity, write_calib_txt, write_imu_txt, write_tum

    write_calib_txt(out / "calib.txt", camera)
    write_tum(out / "groundtruth.txt", motion.trajectory(config.gt_rate))
    gt_t = sample_times(config.duration, config.gt_rate)
    write_angular_velocity(out / "groundtruth_angular_velocity.txt", gt_t, motion.omega(gt_t))
    write_imu_txt(out / "imu.txt", imu)
    iio.imwrite(out / "panorama.png", np.round(np.clip(panorama, 0, 1) * 255).astype(np.uint8))


def _write_json(path: Path, info: dict) -> None:
    path.write_text(json.dumps(info, indent=2) + "\n", encoding="utf-8")


EVENT_FORMATS = ("txt", "h5", "both")  # events.txt (ECD text), events.h5 (smaller, reads faster), or both


def _check_format(events_format: str) -> None:
    if events_format not in EVENT_FORMATS:
        raise InputError(f"events format must be one of {', '.join(EVENT_FORMATS)}, got {events_format!r}")


def write_sequence(seq: SimulatedSequence, out_dir, events_format: str = "both") -> Path:
    """Write an in-memory sequence as an ECD-layout folder (all-or-nothing); ``events_format``: txt, h5 or both."""
    from ..io import write_events_h5, write_events_txt

    _check_format(events_format)
    with OutputDir(out_dir) as out:
        if events_format in ("txt", "both"):
            write_events_txt(out / "events.txt", seq.events)
        if events_format in ("h5", "both"):
            write_events_h5(out / "events.h5", seq.events, camera=seq.camera)
        _write_static(out, seq.config, seq.camera, seq.motion, seq.imu, seq.panorama)
        _write_json(out / "simulation.json", seq.info)
    return Path(out_dir)


def simulate_to_folder(config: SimulatorConfig | None = None, out_dir=".", *, show_progress: bool = True,
                       events_format: str = "both", **overrides) -> dict:
    """Simulate and stream events chunk by chunk into ``out_dir`` (memory stays bounded); ``events_format``:
    events.txt, events.h5 or both.

    Returns the info written to simulation.json. On any failure nothing is left behind.
    """
    from ..io import EventsH5Writer, EventsTxtWriter

    _check_format(events_format)
    config = _as_config(config, overrides)
    start = time.perf_counter()
    with OutputDir(out_dir) as out:
        s = _setup(config)
        bar, update = _progress(config, show_progress)
        n = 0
        try:
            with contextlib.ExitStack() as stack:
                writers = []
                if events_format in ("txt", "both"):
                    writers.append(stack.enter_context(EventsTxtWriter(out / "events.txt")))
                if events_format in ("h5", "both"):
                    writers.append(stack.enter_context(EventsH5Writer(out / "events.h5", s.camera)))
                for chunk in generate_events(s.motion, s.camera, s.log_pano, config, s.times, update):
                    for w in writers:
                        w.append(chunk)
                    n += len(chunk)
        finally:
            if bar is not None:
                bar.close()
        _write_static(out, config, s.camera, s.motion, s.imu, s.panorama)
        info = _info(config, s, n, time.perf_counter() - start)
        _write_json(out / "simulation.json", info)
    return info
