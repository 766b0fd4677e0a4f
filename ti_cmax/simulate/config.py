"""Configuration of the rotational event simulator (a frozen dataclass, loadable with ``load_config``)."""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass

from ..camera import SENSORS
from ..config import Params, param
from ..errors import InputError

SCENES = ("bicycle", "city", "street", "town", "bay", "stars")
TRAJECTORIES = ("random", "pan", "constant")


@dataclass(frozen=True)
class SimulatorConfig(Params):
    # scene -----------------------------------------------------------------------------------
    scene: str = param("city", "procedural scene (ignored when image is given)", choices=SCENES)
    image: str = param("", "equirectangular image file as the scene (any size; resampled to the panorama size)")
    pano_height: int = param(0, "panorama height (width = 2 x height)", unit="px", ge=8,
                             zero="about 2 panorama pixels per sensor pixel")
    blur_sigma_px: float = param(0.6, "anti-alias blur of the panorama (latitude-adaptive)", unit="sensor px", ge=0)
    log_eps: float = param(0.01, "L = log(eps + I): keeps log intensity finite on black (star field)", gt=0)
    num_stars: int = param(3000, "stars of the stars scene", ge=0)
    # sensor ----------------------------------------------------------------------------------
    sensor: str = param("DAVIS240C", "sensor model (DAVIS240C is ECD-like, with distortion)", choices=tuple(SENSORS))
    # motion ----------------------------------------------------------------------------------
    duration: float = param(2.0, "length of the sequence", unit="s", gt=0)
    trajectory: str = param("auto", "motion: random (ECD-like ramp), pan (360 deg about vertical), constant; auto: "
                                    "constant for the stars scene (what a star tracker sees), else random",
                            choices=("auto",) + TRAJECTORIES)
    turns: float = param(1.0, "full turns of trajectory=pan (2-3: the camera revisits the first turn's map)", gt=0)
    pan_wobble: float = param(0.0, "peak rate of a seeded random tilt of trajectory=pan, bounded (0: a pure pan)",
                              unit="rad/s", ge=0)
    max_angular_velocity: float = param(5.0, "peak of the random trajectory (reached near the end)", unit="rad/s",
                                        ge=0)
    random_frequency_max: float = param(1.5, "highest frequency of the random angular velocity", unit="Hz", gt=0)
    random_ramp_start: float = param(0.1, "envelope of the random motion at the start, as a fraction of its end "
                                          "(0.1: ECD-like slow start; 1: fast from the first 5 % on)", ge=0)
    constant_rate_deg: float = param(4.0, "rate of trajectory=constant (star tracking)", unit="deg/s", ge=0)
    rotation_axis: tuple[float, ...] = param((), "camera-frame axis of trajectory=constant (3 numbers; empty: "
                                                 "seeded random axis)")
    integration_rate: float = param(10000.0, "exact-exp integration rate of the ground truth", unit="Hz", gt=0)
    # events ----------------------------------------------------------------------------------
    contrast_threshold: float = param(0.0, "log-intensity change that fires an event", gt=0,
                                      zero="the sensor's: 0.2; DVXplorer 0.25, HD 0.35 (their usual event rates)")
    threshold_sigma: float = param(0.03, "per-pixel Gaussian mismatch of the threshold (each polarity)", ge=0)
    threshold_min: float = param(0.01, "thresholds are clipped below at this value", gt=0)
    refractory_period: float = param(0.0, "per-pixel refractory period", unit="s", ge=0)
    noise_rate: float = param(0.0, "background-activity events per pixel per second", unit="Hz", ge=0)
    hot_pixels: int = param(0, "hot pixels: seeded pixels firing on their own at hot_pixel_rate", ge=0)
    hot_pixel_rate: float = param(200.0, "events per second of each hot pixel (Poisson, random polarity)", unit="Hz",
                                  ge=0)
    max_pixel_step: float = param(0.2, "render so that no pixel moves more than this between renders", unit="px",
                                  gt=0)
    max_render_dt: float = param(0.002, "longest interval between renders (slow motion)", unit="s", gt=0)
    time_resolution: float = param(1e-6, "timestamps rounded to this (0: no rounding)", unit="s", ge=0)
    chunk_megabytes: float = param(64.0, "memory of the render buffer per chunk of renders", unit="MB", gt=0)
    # IMU and ground truth --------------------------------------------------------------------
    imu_rate: float = param(1000.0, "IMU sample rate", unit="Hz", gt=0)
    gt_rate: float = param(1000.0, "ground-truth pose rate", unit="Hz", gt=0)
    gyro_bias_std: float = param(0.003, "std of the constant (seeded) gyro bias per axis", unit="rad/s", ge=0)
    gyro_noise_std: float = param(0.003, "gyro noise per sample", unit="rad/s", ge=0)
    acc_noise_std: float = param(0.02, "accelerometer noise per sample", unit="m/s^2", ge=0)
    gravity: float = param(9.81, "gravity magnitude of the accelerometer", unit="m/s^2", ge=0)
    seed: int = param(0, "random seed (motion, thresholds, noise, gyro bias)")

    def _relations(self) -> None:
        if self.rotation_axis and len(self.rotation_axis) != 3:
            raise InputError(f"rotation_axis needs 3 numbers, got {self.rotation_axis!r}")

    @property
    def motion_kind(self) -> str:
        """The trajectory simulated: ``trajectory``, with auto resolved (a star tracker sees a slow constant rotation;
        the random ECD-like motion reaches 5 rad/s, far beyond star tracking)."""
        if self.trajectory != "auto":
            return self.trajectory
        return "constant" if self.scene == "stars" and not self.image else "random"

    def resolved(self) -> "SimulatorConfig":
        """This config with auto and 0 values filled in: the trajectory (:attr:`motion_kind`) and the sensor's
        contrast threshold (done once at the start, so simulation.json and ``SimulatedSequence.config`` hold the
        values used)."""
        changes = {}
        if self.trajectory == "auto":
            changes["trajectory"] = self.motion_kind
        if self.contrast_threshold <= 0:
            from .generate import sensor_contrast_threshold

            changes["contrast_threshold"] = sensor_contrast_threshold(self.sensor)
        return dataclasses.replace(self, **changes) if changes else self
