"""Baseline rotational trackers of the paper's benchmark (Sec. II), dispatched by name through ``BASELINES``.

Each entry maps a method name to a function ``(events, camera, config: BaselineConfig, imu) -> BaselineResult``;
adding a method is one line in ``BASELINES``. ``run_baseline(name, ...)`` is the public entry point.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Callable

from ti_cmax.config import BackendConfig, DatasetConfig, OutputConfig, SlamConfig
from ti_cmax.errors import InputError

from ti_cmax.pipelines.panorama import render_panorama
from ti_cmax.pipelines.sensor_defaults import pano_size
from .cmax_gae import GAEConfig, run_cmax_gae
from .imu import dead_reckoning
from .result import AngularVelocity, BaselineResult, CountedChunks
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


def run_imu(events_or_chunks, camera, config: BaselineConfig = BaselineConfig(), imu=None) -> BaselineResult:
    """IMU dead reckoning (gyro integration from the identity) and the panoramic IWE of the events along it."""
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
