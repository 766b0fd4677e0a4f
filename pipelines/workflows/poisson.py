"""Poisson integration of a panoramic gradient field: periodic in longitude (FFT), Neumann in latitude (DCT).

Least squares on a staggered grid: find M (n rows, w columns) minimizing
    sum_ij (M[i, j+1 mod w] - M[i, j] - gu[i, j])^2 + sum_{i<n-1, j} (M[i+1, j] - M[i, j] - gv[i, j])^2,
whose normal equations are the 5-point Poisson equation  lap M = div g  with periodic columns and reflecting
(Neumann) top/bottom rows. The Laplacian is diagonal in the basis rfft (columns) x DCT-II (rows), so the solve is
exact, O(N log N) (scipy.fft). The constant is fixed by zero mean. When the columns of interest do not wrap
around (a cyclic interval shorter than the width), the same least squares with Neumann ends in both directions
(DCT x DCT) is solved on that interval only (:func:`integrate_box`).

Pixel-centred gradients g (e.g. of the mapping EKFs) are moved to the staggered positions by averaging the two
neighbours (:func:`staggered_from_centred`): the forward difference M[j+1] - M[j] is the gradient at j + 1/2.
"""
from __future__ import annotations

import numpy as np
import scipy.fft as sfft


def staggered_from_centred(gu: np.ndarray, gv: np.ndarray, periodic_u: bool = True):
    """(gu_s, gv_s): gu_s[i, j] ~ dM/du at (i, j + 1/2) (cyclic if periodic_u, else w - 1 columns),
    gv_s[i, j] ~ dM/dv at (i + 1/2, j) (n - 1 rows)."""
    gu = np.asarray(gu, np.float64)
    gv = np.asarray(gv, np.float64)
    gu_s = 0.5 * (gu + np.roll(gu, -1, axis=1)) if periodic_u else 0.5 * (gu[:, :-1] + gu[:, 1:])
    gv_s = 0.5 * (gv[:-1] + gv[1:])
    return gu_s, gv_s


def _laplacian_eigs(n: int, dct: bool) -> np.ndarray:
    """Eigenvalues of the 1D second-difference operator D^T D: Neumann (DCT-II) or periodic (FFT)."""
    k = np.arange(n)
    return 2.0 - 2.0 * np.cos(np.pi * k / n) if dct else 2.0 - 2.0 * np.cos(2.0 * np.pi * k / n)


def integrate_periodic(gu_s: np.ndarray, gv_s: np.ndarray) -> np.ndarray:
    """Least-squares M (n, w) from staggered gradients, periodic in columns: gu_s (n, w), gv_s (n - 1, w)."""
    gu_s = np.asarray(gu_s, np.float64)
    gv_s = np.asarray(gv_s, np.float64)
    n, w = gu_s.shape
    if gv_s.shape != (n - 1, w):
        raise ValueError(f"gv_s must have shape {(n - 1, w)}, got {gv_s.shape}")
    # rhs = Du^T gu + Dv^T gv  (negative divergence; the system is (Du^T Du + Dv^T Dv) M = rhs)
    rhs = np.roll(gu_s, 1, axis=1) - gu_s
    rhs[1:] += gv_s
    rhs[:-1] -= gv_s
    spec = sfft.dct(sfft.rfft(rhs, axis=1), type=2, axis=0, norm="ortho")
    denom = _laplacian_eigs(n, True)[:, None] + _laplacian_eigs(w, False)[None, : w // 2 + 1]
    denom[0, 0] = 1.0
    spec /= denom
    spec[0, 0] = 0.0
    return sfft.irfft(sfft.idct(spec, type=2, axis=0, norm="ortho"), n=w, axis=1)


def integrate_neumann(gu_s: np.ndarray, gv_s: np.ndarray) -> np.ndarray:
    """Least-squares M (n, m) from staggered gradients with free ends in both directions:
    gu_s (n, m - 1), gv_s (n - 1, m)."""
    gu_s = np.asarray(gu_s, np.float64)
    gv_s = np.asarray(gv_s, np.float64)
    n = gv_s.shape[0] + 1
    m = gu_s.shape[1] + 1
    rhs = np.zeros((n, m))
    rhs[:, 1:] += gu_s
    rhs[:, :-1] -= gu_s
    rhs[1:] += gv_s
    rhs[:-1] -= gv_s
    spec = sfft.dctn(rhs, type=2, norm="ortho")
    denom = _laplacian_eigs(n, True)[:, None] + _laplacian_eigs(m, True)[None, :]
    denom[0, 0] = 1.0
    spec /= denom
    spec[0, 0] = 0.0
    return sfft.idctn(spec, type=2, norm="ortho")


def cyclic_interval(mask_cols: np.ndarray) -> tuple[int, int]:
    """Smallest cyclic interval [start, start + length) holding every True column; (0, w) if none or all."""
    cols = np.flatnonzero(mask_cols)
    w = len(mask_cols)
    if len(cols) == 0 or len(cols) == w:
        return 0, w
    gaps = np.diff(np.concatenate([cols, [cols[0] + w]]))  # gap after each occupied column
    i = int(np.argmax(gaps))
    start = int(cols[(i + 1) % len(cols)])
    return start, w - int(gaps[i]) + 1


def integrate_box(gu: np.ndarray, gv: np.ndarray, mask: np.ndarray, margin: int = 2):
    """Log intensity from pixel-centred gradients on the smallest box around ``mask`` (visited pixels).

    Rows: [r0, r1) = visited rows +- margin (clipped, Neumann). Columns: the whole width, periodic, unless the
    visited columns fit in a cyclic interval leaving a gap of more than 2 margin columns (then that interval
    +- margin, Neumann). Returns (M, rows, cols): M (r1 - r0, len(cols)) zero-mean, ``rows`` = slice(r0, r1),
    ``cols`` the map column indices of M's columns (cyclic, increasing from the interval start).
    Returns (None, None, None) when nothing is visited.
    """
    h, w = mask.shape
    rows_any = np.flatnonzero(mask.any(axis=1))
    if len(rows_any) == 0:
        return None, None, None
    r0 = max(int(rows_any[0]) - margin, 0)
    r1 = min(int(rows_any[-1]) + 1 + margin, h)
    if r1 - r0 < 2:
        r0, r1 = max(0, min(r0, h - 2)), min(h, max(r0, 0) + 2)
    start, length = cyclic_interval(mask[r0:r1].any(axis=0))
    if length + 2 * margin < w - 1:
        cols = (start - margin + np.arange(length + 2 * margin)) % w
        gu_b = np.asarray(gu, np.float64)[r0:r1][:, cols]
        gv_b = np.asarray(gv, np.float64)[r0:r1][:, cols]
        m = integrate_neumann(*staggered_from_centred(gu_b, gv_b, periodic_u=False))
    else:
        cols = np.arange(w)
        m = integrate_periodic(*staggered_from_centred(gu[r0:r1], gv[r0:r1], periodic_u=True))
    return m, slice(r0, r1), cols


__all__ = ["staggered_from_centred", "integrate_periodic", "integrate_neumann", "cyclic_interval", "integrate_box"]
