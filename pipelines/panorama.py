"""Render the panoramic IWE of any trajectory (``ti-cmax map``), with its sharpness figures.

Events are streamed; each batch of ``event_batch_size`` events is rotated by the trajectory at the batch's
mid-time (as in the back-end) and voted bilinearly into an equirectangular map (polarity ignored).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Iterable

import numpy as np

from ti_cmax.camera import Camera
from ti_cmax.events import Events
from ti_cmax.kernels.pano import batch_mid_times, vote_map
from ti_cmax.metrics import event_area_percent, gradient_magnitude
from ti_cmax.trajectory import Trajectory


@dataclass
class PanoramaResult:
    image: np.ndarray  # (h, w) float32 counts of warped events
    events_used: int

    def figures(self, lambda0: float = 1.0) -> dict:
        """EA% (lambda0), GM (Sobel, Eq. 24) and variance of the map (as MAP.json)."""
        from ti_cmax.metrics import row_blocks

        img = self.image
        mean = sum(float(np.sum(img[r], dtype=np.float64)) for r, _ in row_blocks(img.shape)) / img.size
        var = sum(float(np.sum((img[r].astype(np.float64) - mean) ** 2)) for r, _ in row_blocks(img.shape)) / img.size
        return {
            "event_area_percent": float(event_area_percent(img, lambda0)),
            "gradient_magnitude": float(gradient_magnitude(img)),
            "variance": var,
            "events": int(self.events_used),
            "width": int(img.shape[1]),
            "height": int(img.shape[0]),
        }


def render_panorama(chunks: Iterable[Events], camera: Camera, trajectory: Trajectory, width: int, height: int,
                    batch_size: int = 100, t_start: float | None = None, t_end: float | None = None) -> PanoramaResult:
    """Vote every event within the trajectory's time range (and [t_start, t_end] if given) into a panorama.

    The range is widened by the rounding of a TUM file's 9-decimal times (``slam``'s own trajectory.txt then covers
    its first and last events; ``at`` clamps there). Batches are counted from the first event used, across chunk
    boundaries, so the map does not depend on how the input was chunked."""
    tol = 1e-9 + 1e-15 * max(abs(trajectory.t_start), abs(trajectory.t_end))
    lo = max(trajectory.t_start - tol, -np.inf if t_start is None else t_start)
    hi = min(trajectory.t_end + tol, np.inf if t_end is None else t_end)
    image = np.zeros((height, width), np.float32)
    used = 0
    carry = Events.empty()  # the head of a batch that the next chunk completes

    def vote(ev: Events) -> None:
        nonlocal used
        mids = batch_mid_times(ev.t, batch_size)
        vote_map(camera.bearings(ev.x, ev.y), trajectory.at(mids), width, height, batch_size=batch_size, out=image)
        used += len(ev)

    for chunk in chunks:
        ev = chunk.slice_time(lo, np.nextafter(hi, np.inf))
        if len(ev) == 0:
            continue
        if len(carry):
            k = min(batch_size - len(carry), len(ev))
            carry, ev = Events.concatenate([carry, ev[:k]]), ev[k:]
            if len(carry) < batch_size:
                continue
            vote(carry)
            carry = Events.empty()
        n_full = len(ev) // batch_size * batch_size
        if n_full:
            vote(ev[:n_full])
        carry = ev[n_full:]
    if len(carry):
        vote(carry)
    return PanoramaResult(image, used)


def map_to_uint8(image: np.ndarray, gamma: float = 0.75, peak: float | None = None) -> np.ndarray:
    """Display form of a map of warped events as in the paper's figures: gamma-corrected, more events = darker;
    ``peak`` (default: the maximum) and above is black."""
    from ti_cmax.plots import map_display

    from ti_cmax.metrics import row_blocks

    image = np.asarray(image)
    out = np.empty(image.shape, np.uint8)
    if peak is None:
        peak = float(image.max()) if image.size else 0.0
    for rows, _ in row_blocks(image.shape):  # bounded float64 temporaries on large maps
        out[rows] = (np.clip(map_display(image[rows], gamma, peak=peak), 0, 1) * 255 + 0.5).astype(np.uint8)
    return out


STRETCH_PERCENTILE = 99.0  # of the pixels with events: the black level of a map image (contrast stretch)


def map_image(image: np.ndarray, gamma: float = 0.75, *, full_sphere: bool = False,
              intensity: bool = False) -> tuple[np.ndarray, dict]:
    """The PNG of a panoramic map and where it lies: (uint8 image, description for the report).

    By default the image is cropped to the observed region (pixels > 0, with a margin; a region across the
    longitude seam stays in one piece, :func:`ti_cmax.plots.observed_window`), so a small patch of the sphere does
    not sit faint in a white equirectangular frame; ``full_sphere`` keeps the whole map. A map of warped events
    (counts) is contrast-stretched (black at the 99th percentile of its event pixels) and drawn dark on white; an
    ``intensity`` map (8-bit grayscale, e.g. SMT's or ``grayscale``'s panorama: 0 = unobserved, bright = bright
    scene) keeps its values and polarity. The description gives the crop in map pixels and its extent in degrees
    (longitude = atan2(X, Z), latitude = atan2(Y, sqrt(X^2 + Z^2)), both of the map frame; latitude grows downwards
    like the rows): ``{"shown", "width", "height", "crop_px": {"rows", "columns"}, "extent_deg": {"longitude",
    "latitude"}, "size_deg"}``; columns and longitudes run west to east and may pass the seam (first > last)."""
    from ti_cmax.plots import observed_window

    image = np.asarray(image)
    h, w = image.shape[:2]
    if full_sphere:
        roll, rows, cols = 0, slice(0, h), slice(0, w)
    else:
        roll, rows, cols = observed_window([image])
        rows = slice(rows.start or 0, h if rows.stop is None else rows.stop)
        cols = slice(cols.start or 0, w if cols.stop is None else cols.stop)
    view = np.roll(image, roll, axis=1)[rows, cols] if roll else image[rows, cols]
    if intensity:
        shown = np.ascontiguousarray(view, dtype=np.uint8)
    else:
        values = view[view > 0]
        if values.size > 4_000_000:  # the percentile of a large map from a regular subsample
            values = values[:: values.size // 4_000_000]
        peak = float(np.percentile(values, STRETCH_PERCENTILE)) if values.size else 0.0
        shown = map_to_uint8(view, gamma, peak=peak)
    c0 = (cols.start - roll) % w
    c1 = (cols.stop - roll - 1) % w + 1  # exclusive
    lon0 = (c0 - w / 2) * 360.0 / w
    lon1 = (c1 - w / 2) * 360.0 / w
    info = {
        "shown": "full sphere" if full_sphere else "observed region",
        "width": int(shown.shape[1]),
        "height": int(shown.shape[0]),
        "crop_px": {"rows": [int(rows.start), int(rows.stop)], "columns": [int(c0), int(c1)]},
        "extent_deg": {"longitude": [lon0, lon1],
                       "latitude": [(rows.start - h / 2) * 180.0 / h, (rows.stop - h / 2) * 180.0 / h]},
        "size_deg": [(cols.stop - cols.start) * 360.0 / w, (rows.stop - rows.start) * 180.0 / h],
    }
    return shown, info


def describe_extent(info: dict) -> str:
    """One line of a map image's extent, for a command's summary."""
    (lon0, lon1), (lat0, lat1) = info["extent_deg"]["longitude"], info["extent_deg"]["latitude"]
    return (f"{info['shown']} {info['size_deg'][0]:.0f} x {info['size_deg'][1]:.0f} deg "
            f"(longitude {lon0:.0f} to {lon1:.0f}, latitude {lat0:.0f} to {lat1:.0f})")
