"""Bilinear voting and sampling: the one implementation shared by every kernel (IWEs, maps, renderers, trackers).

Pixel (row j, column i) is centred at (u, v) = (i, j). A point (u, v) is split into its corner (i0, j0) =
(floor u, floor v) and fractions (fu, fv); the four neighbours (j0 + dj, i0 + di), di, dj in {0, 1}, get the
weights w = (fu if di else 1 - fu) (fv if dj else 1 - fv). Rows outside the image are dropped. Columns are
either bounded (outside ones dropped) or wrapped modulo the width (longitude of a panorama).

Taichi side: :func:`bilinear_funcs` (per float dtype, cached) gives ti.funcs; the corner loops are ti.static, so
a kernel using them compiles to the same straight-line code as a hand-written split. The write mode is the
caller's choice (``ADD`` plain load/add/store for serial or privately owned buffers: fast and bit-reproducible;
``ATOMIC`` for parallel loops; ``CLEAR`` zeroes exactly the pixels a vote touched).
Numpy side (float64 test oracles): :func:`split_numpy`, :func:`corners_numpy`, :func:`vote_numpy`,
:func:`sample_numpy`.
"""
import functools
from types import SimpleNamespace

import numpy as np

from .runtime import ti

ADD, ATOMIC, CLEAR = 0, 1, 2  # write modes of scatter / vote


# ----------------------------------------------------------------------------------------------------------------
# numpy twins
# ----------------------------------------------------------------------------------------------------------------
def split_numpy(u, v):
    """(i0, j0, fu, fv): integer corner (int64) and fractions in [0, 1) of points (u, v)."""
    u = np.asarray(u, dtype=np.float64)
    v = np.asarray(v, dtype=np.float64)
    i0f, j0f = np.floor(u), np.floor(v)
    return i0f.astype(np.int64), j0f.astype(np.int64), u - i0f, v - j0f


def corners_numpy(u, v, width, height, wrap_u=False, clamp_v=False):
    """The four neighbours of each point, in the order (0, 0), (0, 1), (1, 0), (1, 1) of (dj, di).

    Per neighbour: (row, col, ok, weight, d weight/du, d weight/dv); row and col are clipped (or wrapped) into the
    image so they always index it, ok is False where the neighbour is outside (rows outside; columns outside unless
    ``wrap_u``). ``clamp_v`` keeps rows outside as the nearest border row instead (the simulator's renderer).
    """
    i0, j0, fu, fv = split_numpy(u, v)
    out = []
    for dj, wv, dwv in ((0, 1 - fv, -1.0), (1, fv, 1.0)):
        for di, wu, dwu in ((0, 1 - fu, -1.0), (1, fu, 1.0)):
            row, col = j0 + dj, i0 + di
            ok = np.ones(row.shape, bool) if clamp_v else (row >= 0) & (row < height)
            if wrap_u:
                col = col % width
            else:
                ok = ok & (col >= 0) & (col < width)
            out.append((np.clip(row, 0, height - 1), np.clip(col, 0, width - 1), ok, wu * wv, dwu * wv, dwv * wu))
    return out


def vote_numpy(img, u, v, weights=None, wrap_u=False):
    """Add the bilinear votes of points (u, v) (times ``weights``) into ``img`` (h, w) in place; returns img."""
    h, w = img.shape[:2]
    for row, col, ok, wt, _, _ in corners_numpy(u, v, w, h, wrap_u):
        if weights is not None:
            wt = wt * weights
        np.add.at(img, (row[ok], col[ok]), wt[ok])
    return img


def sample_numpy(img, u, v, wrap_u=False, clamp_v=False):
    """Bilinear interpolation of ``img`` (h, w) or (h, w, c) at (u, v) and its derivatives d/du, d/dv (float64;
    neighbours outside read 0). Shapes (n,) or (n, c)."""
    img = np.asarray(img)
    h, w = img.shape[:2]
    shape = np.shape(u) + img.shape[2:]
    val, du, dv = np.zeros(shape), np.zeros(shape), np.zeros(shape)
    for row, col, ok, wt, dwu, dwv in corners_numpy(u, v, w, h, wrap_u, clamp_v):
        a = img[row, col].astype(np.float64)
        a = np.where(ok.reshape(ok.shape + (1,) * (a.ndim - ok.ndim)), a, 0.0)
        expand = (slice(None),) + (None,) * (a.ndim - 1)
        val += wt[expand] * a
        du += dwu[expand] * a
        dv += dwv[expand] * a
    return val, du, dv


# ----------------------------------------------------------------------------------------------------------------
# Taichi funcs
# ----------------------------------------------------------------------------------------------------------------
@functools.cache
def bilinear_funcs(dtype) -> SimpleNamespace:
    """ti.funcs (split, wrap_cols, col_ok, in_range, scatter, gather, interp, vote, vote_wrap, sample) for one float
    dtype."""
    vec4 = ti.types.vector(4, dtype)

    @ti.func
    def split(u, v):
        """(i0, j0, fu, fv): corner (i32) and fractions of the point (u, v)."""
        i0f = ti.floor(u)
        j0f = ti.floor(v)
        return ti.cast(i0f, ti.i32), ti.cast(j0f, ti.i32), u - i0f, v - j0f

    @ti.func
    def wrap_cols(i0, width):
        """Columns i0 and i0 + 1 modulo the width: branches for i0 in [-width, 2 width) (every caller's range), an
        integer modulo beyond it (a non-finite point must not index outside the image)."""
        ia = i0
        if ia < 0:
            ia += width
        if ia >= width:
            ia -= width
        if ia < 0 or ia >= width:
            ia = ia % width
            if ia < 0:
                ia += width
        ib = ia + 1
        if ib >= width:
            ib -= width
        return ia, ib

    @ti.func
    def col_ok(i0, width):
        """Whether columns i0 and i0 + 1 lie in [0, width) (bounded images)."""
        return i0 >= 0 and i0 < width, i0 + 1 >= 0 and i0 + 1 < width

    @ti.func
    def in_range(j, n):
        """0 <= j < n (n >= 0) as one unsigned compare (the two signed ones compiled to two branches)."""
        return ti.cast(j, ti.u32) < ti.cast(n, ti.u32)

    @ti.func
    def corner(row0, nrows, j0, ia, ib, oka, okb, dj: ti.template(), di: ti.template()):
        """(image row, column, kept) of neighbour (j0 + dj, i0 + di); rows kept in [0, nrows), stored at row0 + j."""
        j = j0 + dj
        col = ia
        ok = oka
        if ti.static(di == 1):
            col = ib
            ok = okb
        return row0 + j, col, in_range(j, nrows) and ok

    @ti.func
    def scatter(img: ti.template(), row0, nrows, j0, ia, ib, oka, okb, fu, fv, w, op: ti.template()):
        """Vote weight w at rows j0, j0 + 1 (kept if in [0, nrows), stored at row0 + j) and columns ia, ib (kept if
        oka, okb). Returns the sum of the weights that landed (factored by rows, as the front-end always summed it)."""
        one = ti.cast(1.0, dtype)
        cols = ti.cast(oka, dtype) * (one - fu) + ti.cast(okb, dtype) * fu
        landed = (ti.cast(j0 >= 0 and j0 < nrows, dtype) * (one - fv) * cols
                  + ti.cast(j0 + 1 >= 0 and j0 + 1 < nrows, dtype) * fv * cols) * w
        for dj, di in ti.static(ti.ndrange(2, 2)):
            r, col, ok = corner(row0, nrows, j0, ia, ib, oka, okb, dj, di)
            if ok:
                wt = (fu if di == 1 else one - fu) * (fv if dj == 1 else one - fv) * w
                if ti.static(op == CLEAR):
                    img[r, col] = ti.cast(0.0, dtype)
                elif ti.static(op == ATOMIC):
                    img[r, col] += wt
                else:
                    img[r, col] = img[r, col] + wt
        return landed

    @ti.func
    def gather(img: ti.template(), row0, nrows, j0, ia, ib, oka, okb, ch: ti.template()):
        """Values at the four neighbours (j0, ia), (j0, ib), (j0 + 1, ia), (j0 + 1, ib) as a 4-vector, 0 where the
        neighbour is dropped (same rules as scatter); ``ch`` >= 0 reads channel ch of an (h, w, c) array."""
        a = vec4(0, 0, 0, 0)
        for dj, di in ti.static(ti.ndrange(2, 2)):
            r, col, ok = corner(row0, nrows, j0, ia, ib, oka, okb, dj, di)
            if ok:
                if ti.static(ch < 0):
                    a[2 * dj + di] = ti.cast(img[r, col], dtype)
                else:
                    a[2 * dj + di] = ti.cast(img[r, col, ch], dtype)
        return a

    @ti.func
    def interp(a, fu, fv):
        """Bilinear value of the corner values a = (a00, a01, a10, a11) ((row, col) offsets) and its d/du, d/dv."""
        one = ti.cast(1.0, dtype)
        val = (one - fv) * ((one - fu) * a[0] + fu * a[1]) + fv * ((one - fu) * a[2] + fu * a[3])
        du = (one - fv) * (a[1] - a[0]) + fv * (a[3] - a[2])
        dv = (one - fu) * (a[2] - a[0]) + fu * (a[3] - a[1])
        return val, du, dv

    @ti.func
    def vote(img: ti.template(), u, v, w, op: ti.template()):
        """Bilinear vote of weight w at (u, v) into the (h, w) image, bounded in both directions."""
        i0, j0, fu, fv = split(u, v)
        oka, okb = col_ok(i0, img.shape[1])
        return scatter(img, 0, img.shape[0], j0, i0, i0 + 1, oka, okb, fu, fv, w, op)

    @ti.func
    def vote_wrap(img: ti.template(), u, v, w, op: ti.template()):
        """Bilinear vote with columns modulo the width (u in [-w, 2w)), rows bounded."""
        i0, j0, fu, fv = split(u, v)
        ia, ib = wrap_cols(i0, img.shape[1])
        return scatter(img, 0, img.shape[0], j0, ia, ib, 1, 1, fu, fv, w, op)

    @ti.func
    def sample(img: ti.template(), u, v):
        """Bilinear value of a bounded (h, w) image at (u, v) (neighbours outside read 0) and its d/du, d/dv."""
        i0, j0, fu, fv = split(u, v)
        oka, okb = col_ok(i0, img.shape[1])
        a = gather(img, 0, img.shape[0], j0, i0, i0 + 1, oka, okb, -1)
        return interp(a, fu, fv)

    return SimpleNamespace(split=split, wrap_cols=wrap_cols, col_ok=col_ok, in_range=in_range, scatter=scatter,
                           gather=gather, interp=interp, vote=vote, vote_wrap=vote_wrap, sample=sample)


__all__ = ["ADD", "ATOMIC", "CLEAR", "bilinear_funcs", "split_numpy", "corners_numpy", "vote_numpy", "sample_numpy"]
