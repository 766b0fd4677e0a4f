"""Kernel ``gather`` (kernels/gather.py): the back-end's events as times and table bearings, written in place."""
import numpy as np
import pytest

from ti_cmax import Camera
from ti_cmax.kernels.gather import BearingGather, gather_numpy

DISTORTED = Camera(64, 48, 50.0, 51.0, 31.7, 23.2, (-0.2, 0.05, 0.001, -0.002, 0.0))
UNDISTORTED = Camera(64, 48, 50.0, 51.0, 31.7, 23.2)


def _columns(n, cam, seed=0):
    rng = np.random.default_rng(seed)
    return (np.cumsum(rng.random(n)), rng.integers(0, cam.width, n).astype(np.uint16),
            rng.integers(0, cam.height, n).astype(np.uint16))


@pytest.mark.parametrize("cam, separable", [(DISTORTED, False), (UNDISTORTED, False), (UNDISTORTED, True)])
@pytest.mark.parametrize("start, step, count, offset", [(0, 1, 500, 0), (450, 1, 500, 3), (7, 3, 160, 11),
                                                        (480, 16, 32, 0)])
def test_gather_matches_its_twin_and_the_camera_bearings(ti_runtime, cam, separable, start, step, count, offset):
    """Rows offset.. of the times, columns offset.. of the bearings (3, m): the times and the float32 bearings of
    events start + j step (wrapping at the end of the columns, as in the worker's ring), bit for bit as
    Camera.bearings; nothing else is written."""
    t, x, y = _columns(500, cam)
    lut = cam.separable_bearing_lut if separable else cam.bearing_lut
    out_t, out_b = np.full(600, -1.0), np.full((3, 600), -1.0, np.float32)
    BearingGather(lut, cam.width, separable)(t, x, y, start, step, count, out_t, out_b, offset)
    want_t, want_b = gather_numpy(t, x, y, lut, cam.width, start, step, count, separable)
    rows = (start + step * np.arange(count)) % len(t)
    assert np.array_equal(want_t, t[rows]) and np.array_equal(want_b, cam.bearings(x[rows], y[rows]).T)
    assert np.array_equal(out_t[offset:offset + count], want_t)
    assert out_b.dtype == np.float32 and np.array_equal(out_b[:, offset:offset + count], want_b)
    outside = np.r_[0:offset, offset + count:600]
    assert np.all(out_t[outside] == -1.0) and np.all(out_b[:, outside] == -1.0)


def test_a_bound_gather_follows_moved_arrays_and_checks_room(ti_runtime):
    """Calls on other arrays (a new ring chunk, a regrown buffer) use them; more events than fit are refused."""
    cam = DISTORTED
    gather = BearingGather(cam.bearing_lut, cam.width)
    for seed in range(3):
        t, x, y = _columns(100 + 50 * seed, cam, seed)
        out_t, out_b = np.zeros(len(t)), np.zeros((3, len(t)), np.float32)
        gather(t, x, y, 0, 1, len(t), out_t, out_b, 0)
        assert np.array_equal(out_t, t) and np.array_equal(out_b, cam.bearings(x, y).T)
    with pytest.raises(ValueError):
        gather(t, x, y, 0, 1, len(t), out_t, out_b, 1)
    with pytest.raises(ValueError):
        gather(t, x, y, 0, 2, len(t) // 2 + 1, out_t, out_b, 0)
    with pytest.raises(ValueError):  # bearings as (m, 3) rows: the kernel would write past them
        gather(t, x, y, 0, 1, 1, out_t[:1], np.zeros((1, 3), np.float32), 0)
