"""Baseline rotational trackers of the paper's benchmark (Sec. II), dispatched by name through ``BASELINES``.

Each entry maps a method name to a function ``(events, camera, config: BaselineConfig, imu) -> BaselineResult``;
adding a method is one line in ``BASELINES``. ``run_baseline(name, ...)`` is the public entry point.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from ti_cmax.config import BackendConfig, DatasetConfig, OutputConfig, SlamConfig
from ti_cmax.errors import InputError
from ti_cmax.events import Events
from ti_cmax.trajectory import Trajectory

from .cmax_gae import GAEConfig, run_cmax_gae
from .rtpt import RTPTConfig, run_rtpt
from .smt import SmtConfig, smt_ekf_baseline, smt_pf_baseline


@dataclass(frozen=True)
class BaselineConfig:
    """All parameters of ``ti-cmax baseline``: the methods' own sections plus what the offline BA (--refine) and
    the IMU map need (backend, output)."""

    dataset: DatasetConfig = field(default_factory=DatasetConfig)
    rtpt: RTPTConfig = field(default_factory=RTPTConfig)
    gae: GAEConfig = field(default_factory=GAEConfig)
    smt: SmtConfig = field(default_factory=SmtConfig)
    backend: BackendConfig = field(default_factory=BackendConfig)
    output: OutputConfig = field(default_factory=OutputConfig)

    def slam_config(self) -> SlamConfig:
        """The SlamConfig of the offline BA run on a baseline's trajectory."""
        return SlamConfig(dataset=self.dataset, backend=self.backend, output=self.output)


@dataclass
class AngularVelocity:
    """Angular velocity estimates of a method that has them (written as angular_velocity.txt)."""

    t: np.ndarray  # (M,) s
    omega: np.ndarray  # (M, 3) rad/s, camera frame

    def __len__(self) -> int:
        return len(self.t)


@dataclass
class BaselineResult:
    """A baseline's trajectory, its own map (h, w) and report (status "ok" or "lost" with lost_at)."""

    trajectory: Trajectory
    map: np.ndarray
    report: dict
    frontend: AngularVelocity | None = None  # name kept from SlamResult: the slam writer reads it
    map_kind: str = "events"  # "events": counts of warped events; "intensity": 8-bit grayscale (SMT)


class CountedChunks:
    """The time-ordered chunks of an Events object, an iterable of chunks or a dataset, counting the events read
    (``count``), so that a baseline streams its input and still reports how much it consumed."""

    def __init__(self, events_or_chunks):
        from ti_cmax.pipelines.frontend import as_chunks

        self._chunks = as_chunks(events_or_chunks)
        self.span = _known_span(events_or_chunks)
        self.count = 0

    def __iter__(self):
        for chunk in self._chunks:
            self.count += len(chunk)
            yield chunk


def _known_span(events_or_chunks) -> float | None:
    """Duration of the input when it is known before reading (Events, dataset), for progress bars."""
    if isinstance(events_or_chunks, Events):
        return float(events_or_chunks.duration) if len(events_or_chunks) else None
    if hasattr(events_or_chunks, "time_range"):
        t0, t1 = events_or_chunks.time_range()
        return float(t1 - t0)
    return None


def run_imu(events_or_chunks, camera, config: BaselineConfig = BaselineConfig(), imu=None) -> BaselineResult:
    """IMU dead reckoning (gyro integration from the identity) and the panoramic IWE of the events along it."""
    from ti_cmax.pipelines.baselines.imu import dead_reckoning
    from ti_cmax.pipelines.panorama import render_panorama
    from ti_cmax.pipelines.sensor_defaults import pano_size

    if imu is None:
        raise InputError("the imu baseline needs IMU data (imu.txt in the dataset folder)")
    tic = time.perf_counter()
    traj = dead_reckoning(imu.t, imu.gyro)
    chunks = CountedChunks(events_or_chunks)
    w, h = pano_size(config.backend, camera)
    pano = render_panorama(chunks, camera, traj, w, h)
    if chunks.count == 0:
        raise InputError("no events to process")
    wall = time.perf_counter() - tic
    report = {"status": "ok", "method": "imu", "events_processed": int(chunks.count), "imu_samples": int(len(imu.t)),
              "wall_seconds": wall, "us_per_event": {"frontend": 0.0},
              "parameters": {"map_size": [int(w), int(h)]}}
    return BaselineResult(traj, pano.image, report)


BASELINES: dict[str, Callable[..., BaselineResult]] = {
    "rtpt": run_rtpt,
    "cmax-gae": run_cmax_gae,
    "imu": run_imu,
    "smt-ekf": smt_ekf_baseline,
    "smt-pf": smt_pf_baseline,
}


def run_baseline(name: str, events, camera, config: BaselineConfig = BaselineConfig(), imu=None,
                 **extra) -> BaselineResult:
    """Run the baseline ``name`` (a key of ``BASELINES``) on events (Events, chunks or a dataset).

    ``extra`` goes to methods that take more inputs (SMT: ``groundtruth`` to bootstrap without IMU,
    ``contrast_threshold``)."""
    try:
        fn = BASELINES[name]
    except KeyError:
        raise InputError(f"unknown baseline {name!r} (expected one of {', '.join(BASELINES)})") from None
    return fn(events, camera, config, imu, **extra)


__all__ = ["BASELINES", "BaselineConfig", "BaselineResult", "AngularVelocity", "RTPTConfig", "GAEConfig",
           "SmtConfig", "run_baseline", "run_rtpt", "run_cmax_gae", "run_imu", "CountedChunks"]
