"""Scenes for the simulator: equirectangular intensity panoramas in [0, 1] in the world frame.

Pixel (u, v) of a w x h panorama (integer = pixel centre) looks along lon = 2 pi (u - w/2) / w,
lat = pi (v - h/2) / h (CONVENTIONS.md). Procedural scenes are mixes of rectangles, ellipses, rings,
lines and checkerboards whose sizes are drawn in degrees on the sphere (their horizontal extent in
panorama pixels is stretched by 1/cos(lat)), placed uniformly over the sphere so there are edges at
all latitudes. The star field is sparse Gaussian dots on black. Every scene is seeded.

The panorama is then blurred with a latitude-adaptive Gaussian (the same angular width everywhere,
so wider in u near the poles) of about half a sensor pixel: the equirectangular panorama is finer
than the sensor near the poles, and without this prefilter bilinear sampling would alias.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
from scipy.ndimage import gaussian_filter1d, zoom

from ..errors import InputError

# scene name -> counts of primitives (per unit sphere coverage) and size range in degrees
_MIXES = {
    #           rect  ellipse ring  line  checker  (min_deg, max_deg)  background contrast
    "bicycle": ((150, 120, 220, 900, 40), (0.8, 14.0), 0.25),
    "city": ((1400, 80, 20, 250, 150), (0.6, 18.0), 0.15),
    "street": ((700, 150, 60, 700, 120), (0.6, 16.0), 0.2),
    "town": ((700, 500, 80, 200, 80), (0.8, 20.0), 0.3),
    "bay": ((120, 350, 30, 120, 20), (1.0, 25.0), 0.5),
}


def lat_lon_grid(h: int, w: int) -> tuple[np.ndarray, np.ndarray]:
    """Latitude of each row (h,) and longitude of each column (w,) in radians."""
    lat = np.pi * (np.arange(h) - h / 2) / h
    lon = 2 * np.pi * (np.arange(w) - w / 2) / w
    return lat, lon


def _paint(img: np.ndarray, rng: np.random.Generator, kind: str, size_deg: float) -> None:
    """Paint one primitive of angular size ``size_deg`` at a uniformly random place on the sphere."""
    h, w = img.shape
    px_per_deg = w / 360.0
    lat_c = np.arcsin(rng.uniform(-1, 1))  # uniform on the sphere
    vc = h / 2 + h * lat_c / np.pi
    uc = rng.uniform(0, w)
    stretch = 1.0 / max(np.cos(lat_c), 0.05)
    a = 0.5 * size_deg * px_per_deg  # half size in equatorial pixels
    b = a * rng.uniform(0.2, 1.0)
    theta = rng.uniform(0, np.pi)
    if kind == "line":
        b = max(0.5 * px_per_deg * rng.uniform(0.15, 0.6), 0.7)
        a = a * rng.uniform(1.0, 3.0)
        theta = rng.choice([0.0, np.pi / 2, rng.uniform(0, np.pi)], p=[0.3, 0.3, 0.4])
    elif kind == "rect":
        theta = rng.choice([0.0, rng.uniform(0, np.pi)], p=[0.7, 0.3])
    reach = np.hypot(a, b) + 1
    v0, v1 = int(max(np.floor(vc - reach), 0)), int(min(np.ceil(vc + reach) + 1, h))
    half_u = min(reach * stretch, w / 2 - 1)
    us = np.arange(int(np.floor(uc - half_u)), int(np.ceil(uc + half_u)) + 1)
    if v1 <= v0 or len(us) == 0:
        return
    x = ((us - uc) / stretch)[None, :]
    y = (np.arange(v0, v1) - vc)[:, None]
    c, s = np.cos(theta), np.sin(theta)
    xr, yr = x * c + y * s, -x * s + y * c
    level = rng.uniform(0.05, 1.0)
    if kind in ("rect", "line"):
        mask = (np.abs(xr) <= a) & (np.abs(yr) <= b)
    elif kind == "ellipse":
        mask = (xr / a) ** 2 + (yr / b) ** 2 <= 1
    elif kind == "ring":
        rr = np.hypot(xr, yr)
        mask = (rr <= a) & (rr >= a * rng.uniform(0.6, 0.9))
    elif kind == "checker":
        cell = max(a / rng.integers(2, 7), 1.5)
        mask = (np.abs(xr) <= a) & (np.abs(yr) <= a)
        odd = (np.floor(xr / cell) + np.floor(yr / cell)) % 2 == 1
        level = np.where(odd, level, rng.uniform(0.05, 1.0))
    else:  # pragma: no cover - internal
        raise ValueError(kind)
    cols = us % w
    block = img[v0:v1][:, cols]
    img[v0:v1, cols] = np.where(mask, level, block)


def procedural_scene(name: str, height: int, seed: int = 0) -> np.ndarray:
    """Seeded textured panorama (height, 2*height) float32 in [0.05, 1] (before anti-aliasing)."""
    if name not in _MIXES:
        raise InputError(f"unknown scene {name!r} (expected one of {', '.join(_MIXES)} or stars)")
    counts, (smin, smax), bg_contrast = _MIXES[name]
    rng = np.random.default_rng([seed, sum(map(ord, name))])
    h, w = height, 2 * height
    # smooth background: low-frequency noise
    coarse = rng.uniform(0, 1, (8, 16))
    bg = zoom(coarse, (h / 8, w / 16), order=3, mode="grid-wrap", grid_mode=True)[:h, :w]
    img = (0.5 + bg_contrast * (bg - 0.5)).astype(np.float32)
    kinds = np.repeat(["rect", "ellipse", "ring", "line", "checker"], counts)
    rng.shuffle(kinds)
    # log-uniform sizes; paint large shapes first so small detail stays on top
    sizes = np.sort(np.exp(rng.uniform(np.log(smin), np.log(smax), len(kinds))))[::-1]
    for kind, size in zip(kinds, sizes):
        _paint(img, rng, str(kind), float(size))
    return np.clip(img, 0.05, 1.0)


def star_field(height: int, num_stars: int, pixel_angle: float, seed: int = 0) -> np.ndarray:
    """Sparse bright Gaussian dots (about one sensor pixel wide) on black, (height, 2*height) float32."""
    rng = np.random.default_rng([seed, 7])
    h, w = height, 2 * height
    img = np.zeros((h, w), np.float32)
    lat = np.arcsin(rng.uniform(-1, 1, num_stars))
    lon = rng.uniform(-np.pi, np.pi, num_stars)
    bright = np.exp(rng.uniform(np.log(0.15), 0.0, num_stars))
    sigma_v = max(0.8 * pixel_angle * h / np.pi, 0.5)
    for la, lo, br in zip(lat, lon, bright):
        vc = h / 2 + h * la / np.pi
        uc = w / 2 + w * lo / (2 * np.pi)
        su = min(sigma_v / max(np.cos(la), 0.02), w / 8)
        rv, ru = int(np.ceil(4 * sigma_v)), int(np.ceil(4 * su))
        vs = np.arange(int(vc) - rv, int(vc) + rv + 2)
        vs = vs[(vs >= 0) & (vs < h)]
        us = np.arange(int(uc) - ru, int(uc) + ru + 2)
        g = br * np.exp(-0.5 * (((vs - vc) / sigma_v) ** 2)[:, None] - 0.5 * (((us - uc) / su) ** 2)[None, :])
        cols = us % w
        img[vs[:, None], cols[None, :]] = np.maximum(img[vs[:, None], cols[None, :]], g.astype(np.float32))
    return img


def load_image(path: str | Path, height: int) -> np.ndarray:
    """An equirectangular image file as grayscale float32 in [0, 1], resampled to (height, 2*height)."""
    import imageio.v3 as iio

    try:
        im = np.asarray(iio.imread(path))
    except FileNotFoundError:
        raise InputError("image file not found", source=str(path)) from None
    except Exception as exc:  # imageio raises many types for unreadable files
        raise InputError(f"cannot read image ({type(exc).__name__}: {exc})", source=str(path)) from None
    if np.issubdtype(im.dtype, np.integer):
        im = im.astype(np.float64) / np.iinfo(im.dtype).max
    im = np.asarray(im, dtype=np.float64)
    if im.ndim == 3:
        im = im[..., :3] @ np.array([0.299, 0.587, 0.114]) if im.shape[2] >= 3 else im[..., 0]
    if im.ndim != 2 or min(im.shape) < 2:
        raise InputError(f"expected a 2-D (gray or color) image, got shape {im.shape}", source=str(path))
    if not np.isfinite(im).all():
        raise InputError("image contains NaN or infinite values", source=str(path))
    lo, hi = float(im.min()), float(im.max())
    if hi > 1.0 or lo < 0.0:  # float images of any range: rescale
        im = (im - lo) / max(hi - lo, 1e-12)
    h, w = height, 2 * height
    out = zoom(im, (h / im.shape[0], w / im.shape[1]), order=1, mode="nearest", grid_mode=True)
    return np.clip(out[:h, :w], 0.0, 1.0).astype(np.float32)


def antialias(img: np.ndarray, sigma_rad: float) -> np.ndarray:
    """Gaussian blur of constant angular width ``sigma_rad`` on the sphere (wider in u near the poles)."""
    if sigma_rad <= 0:
        return img.astype(np.float32, copy=True)
    h, w = img.shape
    lat, _ = lat_lon_grid(h, w)
    out = gaussian_filter1d(img.astype(np.float32), sigma_rad * h / np.pi, axis=0, mode="nearest")
    sig_u = np.minimum(sigma_rad * w / (2 * np.pi) / np.maximum(np.cos(lat), 1e-6), w / 8)
    for r in range(h):
        out[r] = gaussian_filter1d(out[r], sig_u[r], mode="wrap")
    return out


def default_pano_height(pixel_angle: float) -> int:
    """About two panorama pixels per sensor pixel at the equator, rounded to a multiple of 64."""
    h = np.pi / (0.5 * pixel_angle)
    return int(np.clip(64 * np.ceil(h / 64), 256, 4096))


def make_panorama(config, pixel_angle: float) -> np.ndarray:
    """The scene of a SimulatorConfig as intensity (h, 2h) float32 in [0, 1], anti-aliased.

    ``pixel_angle``: angular size of a sensor pixel at the image centre (rad), i.e. 1/f.
    """
    h = int(config.pano_height) or default_pano_height(pixel_angle)
    if config.image:
        img = load_image(config.image, h)
    elif config.scene == "stars":
        img = star_field(h, config.num_stars, pixel_angle, config.seed)
    else:
        img = procedural_scene(config.scene, h, config.seed)
    return np.clip(antialias(img, config.blur_sigma_px * pixel_angle), 0.0, 1.0)


def log_panorama(intensity: np.ndarray, eps: float) -> np.ndarray:
    """Log intensity log(eps + I), float32 (eps > 0 keeps black finite)."""
    return np.log(eps + np.asarray(intensity, dtype=np.float32)).astype(np.float32)
