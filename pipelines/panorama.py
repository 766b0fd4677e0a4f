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


def map_to_uint8(image: np.ndarray, gamma: float = 0.75) -> np.ndarray:
    """Display form of a map as in the paper's figures: gamma-corrected, more events = darker."""
    from ti_cmax.plots import map_display

    from ti_cmax.metrics import row_blocks

    image = np.asarray(image)
    out = np.empty(image.shape, np.uint8)
    peak = float(image.max()) if image.size else 0.0
    for rows, _ in row_blocks(image.shape):  # bounded float64 temporaries on large maps
        out[rows] = (np.clip(map_display(image[rows], gamma, peak=peak), 0, 1) * 255 + 0.5).astype(np.uint8)
    return out
