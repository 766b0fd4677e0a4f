"""The Gaussian blur of every IWE (front-end and panoramic): one definition of its taps, radius and production pass.

Truncated like scipy.ndimage (radius = int(truncate * sigma + 0.5), truncate 4), so the numpy twins can use
scipy's filters with the same kernel. The production blur of image buffers is OpenCV's separable filter
(SIMD): Taichi 1.7.4's CPU backend does not vectorise its loops, and a 9-tap pass over a 365 x 507 f32 buffer
took 0.6-0.9 ms in Taichi (ndarray or field, per-output or 8-lane accumulation) against 0.08 ms in OpenCV
(1 thread, measured on these machines).
"""
import cv2
import numpy as np

TRUNCATE = 4.0


def blur_radius(sigma: float, truncate: float = TRUNCATE) -> int:
    return int(truncate * float(sigma) + 0.5)


def gaussian_taps(sigma: float, truncate: float = TRUNCATE) -> np.ndarray:
    """Normalized 1-D Gaussian taps g[-R..R]; sigma <= 0 gives [1] (no blur)."""
    if sigma <= 0:
        return np.ones(1)
    r = blur_radius(sigma, truncate)
    x = np.arange(-r, r + 1, dtype=np.float64)
    g = np.exp(-0.5 * (x / sigma) ** 2)
    return g / g.sum()


def set_blur_threads(n: int) -> None:
    """OpenCV's own thread pool follows the Taichi thread count (no oversubscription beside a worker process)."""
    cv2.setNumThreads(max(1, int(n)))


def separable_blur(img: np.ndarray, taps: np.ndarray, wrap_cols: bool = False, out: np.ndarray | None = None):
    """Correlate a 2-D f32/f64 image with the same symmetric 1-D ``taps`` along both axes, in its own dtype.

    Zeros beyond the first and last rows; along the columns zeros too, or cyclic (``wrap_cols``: a full-width
    panorama, whose longitude wraps). ``out`` (same shape and dtype, may be ``img``) receives the result."""
    img = np.ascontiguousarray(img)
    taps = np.ascontiguousarray(taps, dtype=img.dtype)
    r = (len(taps) - 1) // 2
    if out is None:
        out = np.empty_like(img)
    if r == 0:
        np.multiply(img, taps[0], out=out)
        return out
    if wrap_cols:
        padded = np.pad(img, ((0, 0), (r, r)), mode="wrap")
        out[...] = cv2.sepFilter2D(padded, -1, taps, taps, borderType=cv2.BORDER_CONSTANT)[:, r:-r]
    else:
        cv2.sepFilter2D(img, -1, taps, taps, dst=out, borderType=cv2.BORDER_CONSTANT)
    return out
