"""Configuration of the rotational event simulator (a frozen dataclass, loadable with ``load_config``)."""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass

from ..errors import InputError

SCENES = ("bicycle", "city", "street", "town", "bay", "stars")
TRAJECTORIES = ("random", "pan", "constant")


@dataclass(frozen=True)
class SimulatorConfig:
    # scene -----------------------------------------------------------------------------------
    scene: str = "city"  # one of SCENES; ignored when `image` is given
    image: str = ""  # equirectangular image file (any size; resampled to the panorama size)
    pano_height: int = 0  # panorama height (width = 2 x height); 0: about 2 panorama pixels per sensor pixel
    blur_sigma_px: float = 0.6  # anti-alias blur of the panorama, in sensor pixels (latitude-adaptive)
    log_eps: float = 0.01  # L = log(eps + I): keeps log intensity finite on black (star field)
    num_stars: int = 3000
    # sensor ----------------------------------------------------------------------------------
    sensor: str = "DAVIS240C"  # DAVIS240C (ECD-like, distorted), DVS128, DAVIS346, VGA, DVXplorer, HD
    # motion ----------------------------------------------------------------------------------
    duration: float = 2.0  # s
    trajectory: str = "random"  # random (ECD-like ramp), pan (360 deg about vertical), constant
    turns: float = 1.0  # full turns of trajectory=pan (2-3: the camera revisits the first turn's map)
    pan_wobble: float = 0.0  # rad/s, peak of a seeded random wobble added to trajectory=pan (0: a pure pan)
    max_angular_velocity: float = 5.0  # rad/s, peak of the random trajectory (reached near the end)
    random_frequency_max: float = 1.5  # Hz, highest frequency of the random angular velocity
    # envelope of the random motion at the start, as a fraction of its end (0.1: ECD-like slow start; 1: as fast
    # from the first 5 % of the sequence on as at the end)
    random_ramp_start: float = 0.1
    constant_rate_deg: float = 4.0  # deg/s for trajectory=constant (star tracking)
    rotation_axis: tuple[float, ...] = ()  # camera-frame axis for trajectory=constant; empty: seeded random axis
    integration_rate: float = 10000.0  # Hz, exact-exp integration of the ground truth
    # events ----------------------------------------------------------------------------------
    contrast_threshold: float = 0.0  # 0: the sensor's (0.2; DVXplorer 0.25, HD 0.35: their usual event rates)
    threshold_sigma: float = 0.03  # per-pixel Gaussian mismatch of the threshold (each polarity)
    threshold_min: float = 0.01  # thresholds are clipped below at this value
    refractory_period: float = 0.0  # s
    noise_rate: float = 0.0  # background-activity events per pixel per second
    max_pixel_step: float = 0.2  # render so that no pixel moves more than this between renders
    max_render_dt: float = 0.002  # s, longest interval between renders (slow motion)
    time_resolution: float = 1e-6  # s, timestamps rounded to this (0: no rounding)
    chunk_megabytes: float = 64.0  # memory of the render buffer per chunk of renders
    # IMU and ground truth --------------------------------------------------------------------
    imu_rate: float = 1000.0
    gt_rate: float = 1000.0
    gyro_bias_std: float = 0.003  # rad/s, std of the constant (seeded) gyro bias per axis
    gyro_noise_std: float = 0.003  # rad/s per sample
    acc_noise_std: float = 0.02  # m/s^2 per sample
    gravity: float = 9.81
    seed: int = 0

    def __post_init__(self):
        if not self.image and self.scene not in SCENES:
            raise InputError(f"unknown scene {self.scene!r} (expected one of {', '.join(SCENES)} or --image FILE)")
        if self.trajectory not in TRAJECTORIES:
            raise InputError(f"unknown trajectory {self.trajectory!r} (expected one of {', '.join(TRAJECTORIES)})")
        from ..camera import SENSORS

        if self.sensor not in SENSORS:
            raise InputError(f"unknown sensor {self.sensor!r} (expected one of {', '.join(SENSORS)})")
        positive = ("duration", "turns", "max_pixel_step", "max_render_dt", "imu_rate", "gt_rate",
                    "integration_rate", "log_eps", "chunk_megabytes", "threshold_min")
        for name in positive:
            if not getattr(self, name) > 0:
                raise InputError(f"{name} must be positive, got {getattr(self, name)}")
        nonneg = ("contrast_threshold", "threshold_sigma", "refractory_period", "noise_rate", "time_resolution",
                  "gyro_bias_std", "gyro_noise_std", "acc_noise_std", "blur_sigma_px", "pano_height",
                  "max_angular_velocity", "random_ramp_start", "pan_wobble")
        for name in nonneg:
            if getattr(self, name) < 0:
                raise InputError(f"{name} must be >= 0, got {getattr(self, name)}")
        if self.rotation_axis and len(self.rotation_axis) != 3:
            raise InputError(f"rotation_axis needs 3 numbers, got {self.rotation_axis!r}")

    def resolved(self) -> "SimulatorConfig":
        """This config with the sensor's contrast threshold filled in when it is 0 (done once at the start, so
        simulation.json and ``SimulatedSequence.config`` hold the number used)."""
        if self.contrast_threshold > 0:
            return self
        from .generate import sensor_contrast_threshold

        return dataclasses.replace(self, contrast_threshold=sensor_contrast_threshold(self.sensor))
