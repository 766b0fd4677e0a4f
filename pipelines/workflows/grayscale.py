"""Grayscale panorama reconstruction (paper Sec. IV-G2, App. B): the mapping module of SMT (Kim et al., BMVC 2014,
as re-implemented by the paper), reusable by a tracker.

Pipeline: events + rotations -> per-map-pixel EKFs on the log-intensity gradient (kernels/mapping.py, Eq. 38)
-> Poisson integration on the bounding box of visited pixels (pipelines/workflows/poisson.py, periodic in longitude)
-> log-intensity panorama M (defined up to a constant; zero mean on the solved box).

``GrayscaleMapper`` is incremental: ``update(events, rotations)`` any number of times (a tracker passes its
own poses; the per-sensor-pixel memory carries over between calls), ``reconstruct()`` whenever a map is needed.
``reconstruct_panoramas`` streams a dataset once into several mappers (one per map size) for the
``ti-cmax grayscale`` command and times every stage.

Observed area: besides ``visited`` (pixels the EKFs updated, mostly edges), the mapper marks the union of the
camera's fields of view (``observed``, from a 4-pixel grid of sensor bearings at poses every
``coverage_interval`` s, on a coarse map of about 4 sensor pixels per cell, dilated by one cell). Textureless
areas the camera saw are observed but not visited; the Poisson solve fills them smoothly. The 8-bit image
shows the observed part of the solved box; everything else is black.
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Iterable, Sequence

import numpy as np
from scipy.ndimage import binary_dilation

from ti_cmax.camera import Camera
from ti_cmax.config import GrayscaleConfig
from ti_cmax.errors import InputError
from ti_cmax.events import Events
from ti_cmax.kernels import mapping as km
from ti_cmax.kernels.pano import batch_mid_times, equirect_numpy
from ti_cmax.trajectory import Trajectory

from ti_cmax.pipelines.workflows.poisson import integrate_box

C_SYNTHETIC = 0.2  # contrast threshold used by the paper for synthetic data
C_REAL = 0.22  # ... and for real data (its true value is unknown there)


@dataclass
class GrayscaleResult:
    log_intensity: np.ndarray  # (h, w) float32, zero mean on the solved box, NaN outside it
    visited: np.ndarray  # (h, w) bool: updated at least once by its EKF
    observed: np.ndarray  # (h, w) bool: inside some field of view of the camera
    gradient: np.ndarray  # (h, w, 2) float32 EKF means (dM/du, dM/dv)
    stats: dict
    timings: dict  # seconds per stage

    @property
    def shape(self) -> tuple[int, int]:
        return self.log_intensity.shape

    def display_mask(self) -> np.ndarray:
        return self.observed & np.isfinite(self.log_intensity)

    def to_uint8(self, low: float = 1.0, high: float = 99.0) -> np.ndarray:
        """8-bit image: M scaled between its low/high percentiles over the shown pixels; black elsewhere."""
        img = np.zeros(self.shape, np.uint8)
        mask = self.display_mask()
        if not mask.any():
            return img
        vals = self.log_intensity[mask].astype(np.float64)
        lo, hi = np.percentile(vals, [low, high])
        scale = 1.0 / max(hi - lo, 1e-12)
        img[mask] = (np.clip((vals - lo) * scale, 0.0, 1.0) * 254.0 + 1.5).astype(np.uint8)  # 1..255: not black
        return img

    def summary(self) -> dict:
        h, w = self.shape
        return {
            "width": int(w), "height": int(h),
            "visited_fraction": float(self.visited.mean()),
            "observed_fraction": float(self.observed.mean()),
            **{k: int(v) for k, v in self.stats.items()},
            "seconds": {k: float(v) for k, v in self.timings.items()},
        }


class GrayscaleMapper:
    """Incremental EKF gradient map + Poisson reconstruction at one map size (see module doc)."""

    def __init__(self, camera: Camera, width: int, height: int, config: GrayscaleConfig | None = None,
                 contrast_threshold: float | None = None):
        self.camera = camera
        self.width, self.height = int(width), int(height)
        if self.width < 4 or self.height < 2:
            raise InputError(f"map size {width}x{height} is too small")
        self.config = config or GrayscaleConfig()
        c = contrast_threshold if contrast_threshold is not None else self.config.contrast_threshold
        self.contrast = float(c) if c and c > 0 else C_REAL
        self.dtype = np.float64 if self.config.mapping_precision == "f64" else np.float32
        self.state = km.new_map_state(self.width, self.height, camera.width * camera.height,
                                      self.config.initial_gradient_variance, self.dtype)
        self.stats = dict.fromkeys(km.STATS, 0)
        self.timings = {"ekf": 0.0, "coverage": 0.0}
        self.events_seen = 0
        # observed-area mask on a coarse grid (about 4 sensor pixels per cell)
        f = max(camera.fx, camera.fy)
        self._ch = int(min(self.height, max(8, np.ceil(np.pi * f / 4.0))))
        self._cw = int(min(self.width, max(16, round(self._ch * self.width / self.height))))
        self._coarse = np.zeros((self._ch, self._cw), bool)
        ys, xs = np.mgrid[0:camera.height:4, 0:camera.width:4]
        xs = np.concatenate([xs.ravel(), np.full(1, camera.width - 1)])
        ys = np.concatenate([ys.ravel(), np.full(1, camera.height - 1)])
        self._grid = camera.unproject(xs, ys).astype(np.float64)
        self._last_cov_bin = None

    # -- state views for a tracker --------------------------------------------------------------------------
    @property
    def gradient(self) -> np.ndarray:
        return self.state["grad"]

    @property
    def covariance(self) -> np.ndarray:
        """(h, w, 3): P00, P01, P11 of each pixel's gradient EKF."""
        return self.state["cov"]

    @property
    def updates(self) -> np.ndarray:
        return self.state["updates"]

    @property
    def visits(self) -> np.ndarray:
        return self.state["visits"]

    @property
    def visited(self) -> np.ndarray:
        return self.state["updates"] > 0

    # -- updates --------------------------------------------------------------------------------------------
    def update(self, events: Events, rotations: np.ndarray, batch_size: int | None = None,
               bearings: np.ndarray | None = None, batch_times: np.ndarray | None = None) -> dict:
        """Feed events in time order with their poses R_world_from_camera.

        ``rotations``: one per event (len == len(events)), or one per batch of ``batch_size`` consecutive events
        (default ``config.event_batch_size``). ``batch_times`` (the batches' times, default their mid-times) only
        serve the observed-area mask. Returns this call's STATS counts.
        """
        n = len(events)
        if n == 0:
            return dict.fromkeys(km.STATS, 0)
        rot = np.asarray(rotations).reshape(-1, 3, 3)
        if len(rot) == n and batch_size is None:
            bs = 1
        else:
            bs = int(batch_size or self.config.event_batch_size)
            if len(rot) != -(-n // bs):
                raise ValueError(f"{len(rot)} rotations for {n} events: expected one per event or per batch of {bs}")
        if bearings is None:
            bearings = self.camera.bearings(events.x, events.y, dtype=self.dtype)
        pix = km.sensor_index(events.x, events.y, self.camera.width)
        start = time.perf_counter()
        counts = km.ekf_update(self.state, bearings, rot, bs, events.t, events.p, pix, self.width, self.height,
                               self.contrast, self.config.measurement_noise, self.config.outlier_distance_px,
                               self.config.max_updates_per_pixel, self.config.visit_gap)
        self.timings["ekf"] += time.perf_counter() - start
        start = time.perf_counter()
        times = batch_times if batch_times is not None else batch_mid_times(events.t, bs)
        self._mark_coverage(np.asarray(times, np.float64), rot)
        self.timings["coverage"] += time.perf_counter() - start
        out = dict(zip(km.STATS, (int(c) for c in counts)))
        for k, v in out.items():
            self.stats[k] += v
        self.events_seen += n
        return out

    def update_with_trajectory(self, events: Events, trajectory: Trajectory) -> dict:
        """Events within the trajectory's time range, posed at the mid-times of batches of event_batch_size."""
        ev = events.slice_time(trajectory.t_start, np.nextafter(trajectory.t_end, np.inf))
        if len(ev) == 0:
            return dict.fromkeys(km.STATS, 0)
        mids = batch_mid_times(ev.t, self.config.event_batch_size)
        return self.update(ev, trajectory.at(mids), self.config.event_batch_size, batch_times=mids)

    def _mark_coverage(self, times: np.ndarray, rot: np.ndarray) -> None:
        """Mark the coarse cells seen from one pose per coverage_interval bin."""
        bins = np.floor(times / self.config.coverage_interval).astype(np.int64)
        first = np.flatnonzero(np.concatenate([[True], bins[1:] != bins[:-1]]))
        if self._last_cov_bin is not None and bins[first[0]] == self._last_cov_bin:
            first = first[1:]
        if len(first) == 0:
            return
        self._last_cov_bin = int(bins[-1])
        xw = np.einsum("kij,nj->kni", rot[first].astype(np.float64), self._grid).reshape(-1, 3)
        u, v = equirect_numpy(xw, self._cw, self._ch)
        cols = np.floor(u + 0.5).astype(np.int64) % self._cw
        rows = np.clip(np.floor(v + 0.5).astype(np.int64), 0, self._ch - 1)
        self._coarse[rows, cols] = True

    def observed(self) -> np.ndarray:
        """(h, w) bool union of the fields of view so far (coarse cells dilated by one, wrapped in longitude)."""
        c = self._coarse
        padded = np.concatenate([c[:, -1:], c, c[:, :1]], axis=1)
        dil = binary_dilation(padded, structure=np.ones((3, 3), bool))[:, 1:-1]
        ri = (np.arange(self.height) * self._ch) // self.height
        ci = (np.arange(self.width) * self._cw) // self.width
        return dil[ri][:, ci] | self.visited

    # -- reconstruction -------------------------------------------------------------------------------------
    def reconstruct(self) -> GrayscaleResult:
        """Poisson-integrate the current gradient map on the box of visited pixels."""
        start = time.perf_counter()
        visited = self.visited
        g = self.state["grad"]
        m, rows, cols = integrate_box(g[..., 0], g[..., 1], visited)
        log_i = np.full((self.height, self.width), np.nan, np.float32)
        if m is not None:
            log_i[rows, cols] = m
        poisson = time.perf_counter() - start
        timings = dict(self.timings, poisson=poisson)
        return GrayscaleResult(log_i, visited.copy(), self.observed(), np.array(g, np.float32),
                               dict(self.stats, events=self.events_seen), timings)


def resolve_contrast(config: GrayscaleConfig, dataset_path=None) -> float:
    """C: the configured value; else the simulator's (simulation.json beside the events); else 0.22 (real data)."""
    if config.contrast_threshold > 0:
        return float(config.contrast_threshold)
    if dataset_path is not None:
        import json
        from pathlib import Path

        path = Path(dataset_path)
        sim = (path if path.is_dir() else path.parent) / "simulation.json"
        if sim.is_file():
            try:
                return float(json.loads(sim.read_text())["config"]["contrast_threshold"])
            except (KeyError, TypeError, ValueError):
                return C_SYNTHETIC
    return C_REAL


def reconstruct_panoramas(chunks: Iterable[Events], camera: Camera, trajectory: Trajectory,
                          sizes: Sequence[tuple[int, int]], config: GrayscaleConfig | None = None,
                          contrast_threshold: float | None = None, t_start: float | None = None,
                          t_end: float | None = None) -> list[GrayscaleResult]:
    """Stream the events once into one mapper per size; poses at batch mid-times from ``trajectory``.

    Timings per result: 'compile' (kernel compilation / cache load, once), 'poses' (bearings + trajectory
    interpolation, shared by all sizes), 'ekf', 'coverage', 'poisson'.
    """
    config = config or GrayscaleConfig()
    mappers = [GrayscaleMapper(camera, w, h, config, contrast_threshold) for w, h in sizes]
    start = time.perf_counter()
    if mappers:
        km.warm_up(mappers[0].dtype)
    compile_seconds = time.perf_counter() - start
    lo = max(trajectory.t_start, -np.inf if t_start is None else t_start)
    hi = min(trajectory.t_end, np.inf if t_end is None else t_end)
    bs = config.event_batch_size
    dtype = mappers[0].dtype if mappers else np.float32
    pose_seconds = 0.0
    for chunk in chunks:
        ev = chunk.slice_time(lo, np.nextafter(hi, np.inf))
        if len(ev) == 0:
            continue
        start = time.perf_counter()
        mids = batch_mid_times(ev.t, bs)
        rot = trajectory.at(mids)
        bearings = camera.bearings(ev.x, ev.y, dtype=dtype)
        pose_seconds += time.perf_counter() - start
        for mapper in mappers:
            mapper.update(ev, rot, bs, bearings=bearings, batch_times=mids)
    results = []
    for mapper in mappers:
        res = mapper.reconstruct()
        res.timings = {"compile": compile_seconds, "poses": pose_seconds, **res.timings}
        results.append(res)
    return results


def normalized_cross_correlation(a: np.ndarray, b: np.ndarray, mask: np.ndarray | None = None) -> float:
    """NCC of two images over ``mask`` (all finite pixels of both when None)."""
    a = np.asarray(a, np.float64)
    b = np.asarray(b, np.float64)
    m = np.isfinite(a) & np.isfinite(b)
    if mask is not None:
        m &= mask
    x = a[m] - a[m].mean()
    y = b[m] - b[m].mean()
    den = np.sqrt((x * x).sum() * (y * y).sum())
    return float((x * y).sum() / den) if den > 0 else 0.0


def resample_panorama(pano: np.ndarray, width: int, height: int) -> np.ndarray:
    """Equirectangular image resampled to width x height (same projection: pixel i of a width-w map is at
    u = i), with a Gaussian pre-blur when shrinking; wraps in longitude."""
    from scipy.ndimage import gaussian_filter, map_coordinates

    pano = np.asarray(pano, np.float64)
    hh, ww = pano.shape
    sy, sx = hh / height, ww / width
    if sx > 1 or sy > 1:
        pano = gaussian_filter(pano, (0.5 * max(sy, 1) if sy > 1 else 0, 0.5 * max(sx, 1) if sx > 1 else 0),
                               mode=("nearest", "wrap"))
    rr, cc = np.meshgrid(np.arange(height) * sy, np.arange(width) * sx, indexing="ij")
    padded = np.concatenate([pano, pano[:, :1]], axis=1)  # column ww == column 0
    return map_coordinates(padded, [np.clip(rr, 0, hh - 1), cc % ww], order=1, mode="nearest")


__all__ = ["GrayscaleConfig", "GrayscaleMapper", "GrayscaleResult", "reconstruct_panoramas", "resolve_contrast",
           "normalized_cross_correlation", "resample_panorama", "C_SYNTHETIC", "C_REAL"]
