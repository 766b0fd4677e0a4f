"""The Gaussian blur of every IWE (front-end and panoramic): one definition of its taps and radius.

Truncated like scipy.ndimage (radius = int(truncate * sigma + 0.5), truncate 4), so the numpy twins can use
scipy's filters with the same kernel.
"""
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
