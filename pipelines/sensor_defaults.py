"""Defaults derived from the sensor: one rule per parameter, so VGA and HD cameras work without tuning.

The reference's defaults were tuned on 240x180 sensors (DAVIS240C). A parameter left at 0 (or ``auto``) in the
config is derived here from the camera, once, before a run; a value the user sets always wins. The resolved
config holds plain numbers and is what is written beside the outputs, so a rerun with that file is exact.

With P the sensor's pixel count, s = P / 43200 (DAVIS240C = 1) and f = (fx + fy) / 2 in pixels:

- ``frontend_iwe_downsample``   d = the largest integer <= sqrt(6) sigma (sigma = ``frontend_blur_sigma``, sensor
  pixels) whose IWE, ceil(width / d) x ceil(height / d), keeps at least 43 200 pixels: 1 up to DAVIS346, 2 on VGA
  and HD (sigma = 1). A pixel of d x d sensor pixels spreads an event's bilinear vote by d / sqrt(6) sensor pixels
  (rms), no more than the blur, which keeps its width in sensor pixels (sigma / d IWE pixels). Measured on 7
  simulated VGA and HD sequences (5-35 M events/s): with the packet rules below, d = 2 was as accurate as the
  full-resolution IWE on VGA (abs within 8 %) and twice as accurate on HD, whose full-resolution packets (N = 213
  000) span up to the still window at a few M events/s (one omega over 0.1 s), for 2-5x less front-end time;
  d = 2 with the blur at 1 IWE pixel (twice as wide) lost 1 % of the omega scale, abs x2-3 on VGA.
- ``num_events_per_packet``     = 10 000 * max(1, s_iwe), s_iwe = IWE pixels / 43200, rounded to 1000: the IWE
  holds the same events per pixel (0.23) as the reference's 10 000 on a DAVIS240C (a full-resolution VGA IWE of
  10-20k events holds 0.05 events per pixel: the variance is noise and the optimiser stops at once); smaller
  sensors keep the reference's 10 000 (never fewer: smaller packets were not measured).
- ``frontend_max_packet_events`` = (d + 1) * 10 000 * max(1, s_iwe), rounded to 1000 (the thinning cap; -1: off;
  the derived N's multiple whatever N the user sets): the reference's 2N at full resolution; 3N on a coarser IWE
  (VGA 53 000, HD 160 000), where 2N lost 8-60 % of the abs accuracy on the VGA sequences and 3N was within the
  run-to-run spread of the full-resolution front-end (or better, on HD). A packet stretched to the minimum span S
  (``frontend_min_packet_span``, 4 packet steps) shares each event with S / dt packets, so below the cap it keeps at
  most max(2N, its event rate x dt) events (``AngularVelocityEstimator.thinning_step``): each input event is
  evaluated about once per evaluation round, not S / dt times; never fewer than 2N, the reference's cap, since
  caps of N (DAVIS240C) and 1.5N (VGA) doubled the front-end's abs error. HD at 7 M events/s: 281 000-event packets
  thinned to 94 000 instead of 140 000 (front-end abs 0.019 -> 0.021 deg, rel 0.030 -> 0.027 deg/s); at VGA's 12 M
  and DAVIS240C's 2 M events/s the rate x dt is at or above the cap, which rules as before.
- ``frontend_min_event_rate``   = 10 000 * s events/s (still-camera floor): a smaller sensor sees fewer events
  for the same motion, a larger one more.
- ``backend_min_ev_rate``       = 10 000 * s events/s (below it a window is treated as still: no BA).
- ``pano_height``               = W / 2 with W = 2 pi f * ``pano_pixels_per_sensor_pixel`` (1.5) rounded up to a
  multiple of 256, at most 8192: the map's angular resolution follows the camera's (DAVIS240C, f = 199:
  2048 x 1024; DVS128, f = 110: 1280 x 640; VGA, f = 520: 5120 x 2560; HD, f = 1235: 8192 x 4096, the cap, about
  1.06 map pixels per sensor pixel, 400 MB of map state). The back-end's work per window depends on the field
  of view's area in map pixels (about P * ratio^2), not on the map size.
- ``backend_map_downsample``    d = the largest integer <= sqrt(6) sigma (sigma = ``backend_blur_sigma``, map pixels)
  whose BA map (the output map d times coarser per axis, dividing its size) holds the sensor's view in at least
  97 200 pixels, a DAVIS240C's view at the default 1.5 map pixels per sensor pixel (43 200 * 1.5^2); the view holds
  V = P * (map width / (2 pi f))^2 / d^2 BA-map pixels. 1 up to DAVIS346, 2 on VGA and HD. As on the front-end's IWE,
  a pixel of d x d map pixels spreads a vote by d / sqrt(6) map pixels (rms), no more than the blur. The BA's cost
  per evaluation follows the window's events and its area in BA-map pixels, both d^2 smaller (with the cap below);
  the output map keeps the full resolution, and the strides it settles are re-voted onto the BA's map
  (kernels.pano.revote). Measured with the cap below on a VGA (12.6 M events/s) and an HD (7 M events/s) sequence:
  abs 0.034 -> 0.032 and 0.033 -> 0.026 deg, rel 0.031 -> 0.036 and 0.028 -> 0.029 deg/s, for 4x less BA time on
  both. With the blur at 0.5 BA-map pixels instead (its width kept in map pixels), a refinement of the VGA one's
  front-end trajectory had abs 0.037 against 0.027 deg, rel 0.034 against 0.036 deg/s, and 30 % more evaluations.
- ``backend_max_window_events`` = 5 * P * window / 0.2 s, rounded to 1000: a window with more events is sampled
  evenly (every n/cap-th event, so evenly in time and, in proportion, over the image) for the BA; every event still
  goes into the map. 5 events per sensor pixel per 0.2 s window is about 1.1 M events/s on a DAVIS240C and 7.7 M
  events/s on a VGA sensor at d = 1; on a VGA sequence at 10.5 M events/s, sampling to it (66 % of the events) left
  the abs error unchanged (0.032 deg) and halved the back-end's work. On a coarser BA map (d > 1) the cap is
  expressed per BA-map pixel: at most 5 / 1.5^2 = 2.2 events per pixel of the sensor's view on it (V = P * (map
  width / (2 pi f))^2 / d^2), as many per pixel as 5 per sensor pixel give at the default 1.5 map pixels per sensor
  pixel (VGA, f = 520: 419 000; HD: 571 000, whose 8192-wide map has 1.06 map pixels per sensor pixel). On an HD
  sequence (7 M events/s) a cap of 514 000 instead of 1 152 000 (5 P / d^2) kept the abs error (0.022 against
  0.024 deg; 0.033 at d = 1) for 1.8x less BA time.
- ``loop_registration_events``  = 20 000 * max(1, s), rounded to 1000: the recent events a loop verification
  registers hold as many events per map pixel as 20 000 on a DAVIS240C (maps have 1.5 map pixels per sensor
  pixel on every sensor below the 8192 cap). On a VGA pan (bay, 8 s, 2 turns) the first revisit registered with
  20 000 events correlated 0.046 with the old map (rejected, with a false 0.10 deg correction), with 142 000
  0.561 (accepted, 0.012 deg: no drift to close); its verification then took 16 s instead of 7 (load 6-7).
- ``loop_min_travel``           = 360 deg - 2 * the horizontal field of view (the angle between the bearings of the
  left and right image edges on the centre row, distortion included), rounded to 1 deg (DAVIS240C 219, DVS128 239,
  VGA 216, HD 248 deg): a map region also counts as old for the loop closer (a revisit) once the camera turned
  that far since it last saw it (``loop_min_age`` alone, 3 s, missed the revisits of a fast pan: 2 turns in 6 s
  come back to the start 1.7-2.5 s after they left it). On a pan a region seen again has been left behind for a
  turn less one field of view of rotation; the margin of a second field of view covers the wobble and the
  region's width, and swings back and forth over a field of view or two never add up to it while the region is
  out of view. A view of 180 deg or more gives -1 (the age alone).
- ``realtime_min_window_events`` = a fifth of the cap above (P * window / 0.2 s at d = 1), rounded to 1000: the
  floor below which the real-time controller (pipelines/realtime.py) never samples a window's BA (fewer events per
  pixel leave the panoramic IWE too sparse for its variance to mean much).
"""
from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from ti_cmax.camera import Camera
from ti_cmax.config import BackendConfig, FrontendConfig, SlamConfig
from ti_cmax.errors import InputError

REFERENCE_PIXELS = 240 * 180  # DAVIS240C, the sensor the reference's defaults were tuned on
REFERENCE_PACKET_EVENTS = 10_000
REFERENCE_MIN_EVENT_RATE = 10_000.0  # events/s
REFERENCE_REGISTRATION_EVENTS = 20_000  # loop verification on a DAVIS240C
WINDOW_EVENTS_PER_PIXEL = 5.0  # per 0.2 s window
REALTIME_MIN_WINDOW_FRACTION = 0.2  # of the window cap
DEFAULT_MAP_SCALE = 1.5  # map pixels per sensor pixel (pano_pixels_per_sensor_pixel's default)
REFERENCE_VIEW_PIXELS = REFERENCE_PIXELS * DEFAULT_MAP_SCALE**2  # a DAVIS240C's view at the default map scale
MAP_WIDTH_MULTIPLE = 256
MAX_MAP_WIDTH = 8192  # 8192 x 4096: 33 M pixels, about 400 MB of map state (raw, blurred, scratch; float32)


def _pixel_scale(camera: Camera) -> float:
    return camera.width * camera.height / REFERENCE_PIXELS


def _round_to(value: float, step: int) -> int:
    return int(max(step, step * round(value / step)))


def iwe_downsample_for(camera: Camera, blur_sigma: float = 1.0) -> int:
    """The front-end IWE's downsampling factor d for this camera and blur (sensor pixels; see the module docstring):
    the largest d <= sqrt(6) sigma whose IWE keeps at least the reference sensor's pixel count."""
    d = max(1, int(math.floor(math.sqrt(6.0) * float(blur_sigma) + 1e-9)))
    while d > 1 and (-(-camera.width // d)) * (-(-camera.height // d)) < REFERENCE_PIXELS:
        d -= 1
    return d


def iwe_size(camera: Camera, downsample: int) -> tuple[int, int]:
    """(width, height) of the front-end's IWE at downsampling factor d: ceil(sensor size / d)."""
    d = int(downsample)
    return -(-camera.width // d), -(-camera.height // d)


def derived_frontend(camera: Camera, config: FrontendConfig = FrontendConfig()) -> dict:
    """The front-end values the rules give for this camera (see the module docstring); the packet sizes follow
    the IWE's pixels, at the config's downsampling factor when set."""
    d = config.frontend_iwe_downsample or iwe_downsample_for(camera, config.frontend_blur_sigma)
    w, h = iwe_size(camera, d)
    s_iwe = w * h / REFERENCE_PIXELS
    return {
        "frontend_iwe_downsample": d,
        "num_events_per_packet": _round_to(REFERENCE_PACKET_EVENTS * max(1.0, s_iwe), 1000),
        "frontend_max_packet_events": _round_to(REFERENCE_PACKET_EVENTS * max(1.0, s_iwe) * (d + 1), 1000),
        "frontend_min_event_rate": round(REFERENCE_MIN_EVENT_RATE * _pixel_scale(camera), 1),
    }


def map_width_for(camera: Camera, pixels_per_sensor_pixel: float) -> int:
    """Panorama width whose angular resolution matches the camera's at the image centre (times the ratio)."""
    focal = 0.5 * (camera.fx + camera.fy)
    width = MAP_WIDTH_MULTIPLE * math.ceil(2 * math.pi * focal * pixels_per_sensor_pixel / MAP_WIDTH_MULTIPLE)
    return min(width, MAX_MAP_WIDTH)


def _view_scale(camera: Camera, width: int) -> float:
    """Map pixels per sensor pixel at the image centre on a map ``width`` pixels around."""
    return width / (2 * math.pi * 0.5 * (camera.fx + camera.fy))


def ba_downsample_for(camera: Camera, width: int, height: int, blur_sigma: float = 1.0) -> int:
    """The BA map's downsampling factor d of a ``width`` x ``height`` map for this camera and blur (map pixels; see
    the module docstring): the largest d <= sqrt(6) sigma dividing the map's size whose BA map keeps the sensor's view
    in at least REFERENCE_VIEW_PIXELS pixels."""
    view = camera.width * camera.height * _view_scale(camera, width) ** 2
    d = max(1, int(math.floor(math.sqrt(6.0) * float(blur_sigma) + 1e-9)))
    while d > 1 and (width % d or height % d or view / (d * d) < REFERENCE_VIEW_PIXELS):
        d -= 1
    return d


def window_cap_for(camera: Camera, width: int, d: int, window: float) -> float:
    """backend_max_window_events before rounding (see the module docstring): 5 events per sensor pixel per 0.2 s;
    on a coarser BA map (d > 1) at most as many per BA-map pixel of the sensor's view as that gives at the default
    map scale."""
    pixels = camera.width * camera.height
    view = pixels * (_view_scale(camera, width) / d) ** 2
    per_pixel = 1.0 if d == 1 else min(1.0, view / (pixels * DEFAULT_MAP_SCALE**2))
    return WINDOW_EVENTS_PER_PIXEL * pixels * per_pixel * window / 0.2


def derived_backend(camera: Camera, config: BackendConfig = BackendConfig()) -> dict:
    """The back-end values the rules give for this camera (see the module docstring); the BA map's factor and the
    window cap follow the map's size and the factor the config sets, when it sets them."""
    pixels = camera.width * camera.height
    s = pixels / REFERENCE_PIXELS
    height = config.pano_height or map_width_for(camera, config.pano_pixels_per_sensor_pixel) // 2
    width = config.pano_width or 2 * height
    d = config.backend_map_downsample or ba_downsample_for(camera, width, height, config.backend_blur_sigma)
    return {
        "pano_height": height,
        "backend_min_ev_rate": round(REFERENCE_MIN_EVENT_RATE * s, 1),
        "backend_map_downsample": d,
        "backend_max_window_events": _round_to(window_cap_for(camera, width, d, config.backend_time_window_size), 1000),
    }


def derived_loop(camera: Camera) -> dict:
    """The loop closer's values for this camera (see the module docstring)."""
    events = REFERENCE_REGISTRATION_EVENTS * max(1.0, _pixel_scale(camera))
    edges = camera.unproject(np.array([-0.5, camera.width - 0.5]), np.full(2, camera.cy))
    edges /= np.linalg.norm(edges, axis=1, keepdims=True)
    fov = math.degrees(math.acos(float(np.clip(edges[0] @ edges[1], -1.0, 1.0))))
    travel = float(round(360.0 - 2 * fov))
    # a view of 180 deg or more (a fisheye): no turn leaves a region behind for long; the age alone (-1)
    return {"loop_registration_events": _round_to(events, 1000), "loop_min_travel": travel if travel > 0 else -1.0}


def derived_realtime(camera: Camera, backend: BackendConfig = BackendConfig()) -> dict:
    """The real-time controller's values for this camera (see the module docstring)."""
    b = derived_backend(camera, backend)
    cap = window_cap_for(camera, 2 * b["pano_height"] if not backend.pano_width else backend.pano_width,
                         b["backend_map_downsample"], backend.backend_time_window_size)
    return {"realtime_min_window_events": _round_to(cap * REALTIME_MIN_WINDOW_FRACTION, 1000)}


def _fill(section, values: dict):
    """Replace the fields left at 0 (derived) by the rule's value; user values stay."""
    return replace(section, **{k: v for k, v in values.items() if getattr(section, k) == 0})


def resolve_frontend(config: FrontendConfig, camera: Camera) -> FrontendConfig:
    return _fill(config, derived_frontend(camera, config))


def resolve_backend(config: BackendConfig, camera: Camera) -> BackendConfig:
    """The back-end's config with its derived values; InputError when a set BA-map factor does not divide the map."""
    resolved = _fill(config, derived_backend(camera, config))
    (width, height), d = resolved.pano_size, resolved.backend_map_downsample
    if width % d or height % d:
        raise InputError(f"backend_map_downsample={d} must divide the map's size {width} x {height} (pano_width, "
                         f"pano_height)")
    return resolved


def pano_size(config: BackendConfig, camera: Camera) -> tuple[int, int]:
    """(width, height) of the back-end's map for this camera (the user's size, or the derived one)."""
    return resolve_backend(config, camera).pano_size


def resolve_config(config: SlamConfig, camera: Camera) -> SlamConfig:
    """The config with every derived (0) value replaced by its rule's number for this camera. Idempotent."""
    return replace(config, frontend=resolve_frontend(config.frontend, camera),
                   backend=resolve_backend(config.backend, camera),
                   realtime=_fill(config.realtime, derived_realtime(camera, config.backend)),
                   loop=_fill(config.loop, derived_loop(camera)))


def derived_summary(config: SlamConfig, camera: Camera) -> dict:
    """The values the rules set (not those the user gave), for the command's summary and report.json."""
    resolved = resolve_config(config, camera)
    out = {}
    for section in ("frontend", "backend", "loop"):
        before, after = getattr(config, section), getattr(resolved, section)
        for key in list(derived_frontend(camera)) + list(derived_backend(camera, config.backend)) + \
                list(derived_loop(camera)):
            if hasattr(before, key) and getattr(before, key) != getattr(after, key):
                out[key] = getattr(after, key)
    return out


def describe(values: dict) -> str:
    """One line for a command's summary: the derived values, as numbers."""
    return ", ".join(f"{k}={v:g}" if isinstance(v, float) else f"{k}={v}" for k, v in values.items())


__all__ = ["iwe_downsample_for", "ba_downsample_for",
           "iwe_size", "resolve_config", "resolve_frontend", "resolve_backend",
           "derived_frontend", "derived_backend", "derived_summary", "describe", "map_width_for", "pano_size",
           "derived_realtime", "derived_loop"]
