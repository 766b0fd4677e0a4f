"""CMax-SLAM at super-resolution (paper Sec. IV-G1, Fig. 15, 16): the same events run through CMax-SLAM with
panoramic maps of several sizes; per size, the panoramic IWE of the estimated trajectory rendered at that
size, the back-end runtime per event (Fig. 16a) and the map's quality figures.

Image quality (Fig. 16b): the paper uses NIQE and PIQE. NIQE needs a model fitted on pristine images (the
MATLAB/pyiqa parameters, downloaded at run time): unavailable offline. PIQE needs no model: it is computed with
the ``pypiqe`` package when it is importable (it needs opencv); otherwise it is reported as unavailable.
GM (gradient magnitude) and EA% (event area) from ``ti_cmax.metrics`` are always reported (higher GM and
lower EA mean a sharper map), on the central part of the map (the paper's "central parts").

Memory: the back-end and the renderer only ever touch bounding boxes of the pixels a batch votes into, so an
8192x4096 map costs its own storage (a few dense float32 maps of 134 MB) and no per-event images. Sizes are
run one at a time and each size's map is handed to the caller (``on_size``) and then dropped.
"""
from __future__ import annotations

import resource
import time
from dataclasses import dataclass, field
from typing import Callable, Iterable

import numpy as np

from ti_cmax.camera import Camera
from ti_cmax.config import SlamConfig, parse_map_sizes, update_config
from ti_cmax.errors import InputError
from ti_cmax.metrics import evaluate_rotations, event_area_percent, gradient_magnitude
from ti_cmax.outputs import peak_rss_mb
from ti_cmax.pipelines.panorama import map_to_uint8, render_panorama
from ti_cmax.pipelines.slam import run_slam
from ti_cmax.trajectory import Trajectory

DEFAULT_SIZES = ((512, 256), (1024, 512), (2048, 1024), (4096, 2048), (8192, 4096))
CENTRAL_FRACTION = 0.5  # quality figures on the central half (in both directions) of the visited region


def parse_sizes(text: str) -> list[tuple[int, int]]:
    """'512x256,1024x512' -> [(512, 256), (1024, 512)] (width x height; the projection needs w = 2 h)."""
    sizes = parse_map_sizes(text, "--sizes")  # the back-end's bounds (BackendConfig pano_width, pano_height)
    for w, h in sizes:
        if w != 2 * h:
            raise InputError(f"--sizes {w}x{h}: the equirectangular map needs width = 2 x height")
    return sizes


def current_rss_mb() -> float:
    try:
        with open("/proc/self/statm") as fh:
            return int(fh.read().split()[1]) * resource.getpagesize() / (1024.0 * 1024.0)
    except OSError:
        return float("nan")


def central_crop(image: np.ndarray, fraction: float = CENTRAL_FRACTION) -> np.ndarray:
    """Central part of the visited bounding box (the part of the map every size sees alike)."""
    ys, xs = np.nonzero(image > 0)
    if len(ys) == 0:
        return image
    y0, y1, x0, x1 = ys.min(), ys.max() + 1, xs.min(), xs.max() + 1
    cy, cx = (y0 + y1) / 2, (x0 + x1) / 2
    hh, hw = max((y1 - y0) * fraction / 2, 4), max((x1 - x0) * fraction / 2, 4)
    return image[int(max(cy - hh, 0)):int(cy + hh), int(max(cx - hw, 0)):int(cx + hw)]


def piqe_score(image_u8: np.ndarray) -> float | None:
    """PIQE of an 8-bit grayscale image with pypiqe, or None when it is not installed."""
    try:
        from pypiqe import piqe
    except Exception:  # ImportError, or its opencv dependency missing/broken
        return None
    return float(piqe(image_u8)[0])


def quality_figures(image: np.ndarray, gamma: float = 0.75, lambda0: float = 1.0) -> dict:
    """GM and EA% of the central part; PIQE of its display form when available; NIQE unavailable."""
    crop = central_crop(np.asarray(image, dtype=np.float64))
    out = {
        "central_crop_size": [int(crop.shape[1]), int(crop.shape[0])],
        "gradient_magnitude": gradient_magnitude(crop),
        "event_area_percent": event_area_percent(crop, lambda0),
        "gradient_magnitude_full": gradient_magnitude(image),
        "event_area_percent_full": event_area_percent(image, lambda0),
    }
    display = map_to_uint8(crop, gamma)
    # GM of the display form (gamma, scaled to the map's peak): comparable across sizes, unlike raw counts
    out["gradient_magnitude_display"] = gradient_magnitude(display.astype(np.float64) / 255.0)
    p = piqe_score(display)
    out["piqe"] = p
    out["niqe"] = None
    return out


def quality_availability() -> dict:
    try:
        import pypiqe  # noqa: F401

        piqe = "pypiqe"
    except Exception:
        piqe = "unavailable: the pypiqe package (and opencv) is not installed"
    return {"piqe": piqe,
            "niqe": "unavailable: needs a model fitted on pristine images (pyiqa/MATLAB parameters, downloaded "
                    "at run time); no offline implementation",
            "reported": "gradient_magnitude (raw counts; and of the display image, comparable across sizes; "
                        "higher = sharper), event_area_percent (lower = sharper), on the central crop"}


@dataclass
class SizeResult:
    width: int
    height: int
    map: np.ndarray | None  # rendered IWE at this size (None once the caller dropped it)
    trajectory: Trajectory
    us_per_event_backend: float
    us_per_event_frontend: float
    slam_wall_seconds: float
    render_seconds: float
    peak_rss_mb: float
    rss_after_mb: float
    quality: dict
    errors: dict | None = None
    slam_report: dict = field(default_factory=dict)

    def row(self) -> dict:
        r = {
            "size": f"{self.width}x{self.height}", "width": self.width, "height": self.height,
            "events_processed": self.slam_report.get("events_processed"),
            "us_per_event_backend": self.us_per_event_backend, "us_per_event_frontend": self.us_per_event_frontend,
            "slam_wall_seconds": self.slam_wall_seconds, "render_seconds": self.render_seconds,
            "peak_rss_mb": self.peak_rss_mb, "rss_after_mb": self.rss_after_mb,
            "windows_optimized": self.slam_report.get("backend", {}).get("windows_optimized"),
            "backend_mean_iterations": self.slam_report.get("backend", {}).get("mean_iterations"),
            **{f"quality_{k}": v for k, v in self.quality.items()},
        }
        if self.errors:
            r.update(self.errors)
        return r


def iter_super_resolution(source: Callable[[], Iterable], camera: Camera, sizes, config: SlamConfig = SlamConfig(),
                          *, groundtruth: Trajectory | None = None, render: bool = True,
                          progress_total: float | None = None):
    """Yield one :class:`SizeResult` per map size (CMax-SLAM with pano_width x pano_height = size, then the IWE
    of its trajectory rendered at that size). ``source()`` returns a fresh iterable of event chunks."""
    for w, h in sizes:
        cfg = update_config(config, {"pano_width": int(w), "pano_height": int(h)}, source="super-resolution")
        res = run_slam(source(), camera, cfg, progress_total=progress_total)
        us = res.report["us_per_event"]
        tic = time.perf_counter()
        if render:
            image = render_panorama(source(), camera, res.trajectory, w, h, cfg.backend.event_batch_size).image
        else:
            image = res.map
        render_s = time.perf_counter() - tic
        del res.map
        errors = None
        if groundtruth is not None:
            e = evaluate_rotations(groundtruth, res.trajectory)
            d = e.to_dict()
            errors = {k: d[k] for k in ("abs_rmse_deg", "rel_rmse_deg_per_s")}
        quality = quality_figures(image, cfg.output.gamma, cfg.backend.lambda0)
        yield SizeResult(int(w), int(h), image, res.trajectory, float(us["backend"]), float(us["frontend"]),
                         float(res.report["wall_seconds"]), render_s, peak_rss_mb(), current_rss_mb(), quality,
                         errors, {"backend": res.report["backend"], "frontend": res.report["frontend"],
                                 "events_processed": res.report["events_processed"]})


def runtime_table(rows: list[dict]) -> str:
    """Plain-text table of the per-size figures (Fig. 16a as numbers)."""
    head = f"{'size':>11} {'BA us/ev':>9} {'FE us/ev':>9} {'SLAM s':>8} {'render s':>9} {'peak RSS MB':>12} " \
           f"{'GM(disp)':>8} {'EA%':>7} {'PIQE':>7}"
    lines = [head]
    for r in rows:
        piqe = r.get("quality_piqe")
        lines.append(f"{r['size']:>11} {r['us_per_event_backend']:9.2f} {r['us_per_event_frontend']:9.2f} "
                     f"{r['slam_wall_seconds']:8.1f} {r['render_seconds']:9.2f} {r['peak_rss_mb']:12.0f} "
                     f"{r['quality_gradient_magnitude_display']:8.4f} {r['quality_event_area_percent']:7.2f} "
                     f"{'n/a' if piqe is None else f'{piqe:.2f}':>7}")
    return "\n".join(lines)


__all__ = ["DEFAULT_SIZES", "parse_sizes", "iter_super_resolution", "SizeResult", "quality_figures",
           "quality_availability", "runtime_table", "peak_rss_mb", "central_crop", "piqe_score"]
