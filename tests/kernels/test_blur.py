"""The production blur (OpenCV separable filter) against scipy's correlate1d, the numpy oracle."""
import numpy as np
import pytest
from scipy.ndimage import correlate1d

from ti_cmax.kernels.blur import gaussian_taps, separable_blur


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
@pytest.mark.parametrize("wrap", [False, True])
@pytest.mark.parametrize("sigma", [0.0, 1.0, 2.0])
def test_separable_blur_matches_scipy(dtype, wrap, sigma):
    img = np.random.default_rng(3).random((37, 53)).astype(dtype)
    taps = gaussian_taps(sigma)
    ref = correlate1d(img.astype(np.float64), taps, axis=1, mode="wrap" if wrap else "constant")
    ref = correlate1d(ref, taps, axis=0, mode="constant")
    out = separable_blur(img, taps, wrap_cols=wrap)
    assert out.dtype == dtype and out.shape == img.shape
    np.testing.assert_allclose(out, ref, atol=2e-6 if dtype == np.float32 else 1e-13)
    inplace = img.copy()
    separable_blur(inplace, taps, wrap_cols=wrap, out=inplace)
    np.testing.assert_array_equal(inplace, out)


def test_wrap_moves_mass_across_the_seam():
    img = np.zeros((9, 20), np.float32)
    img[4, 0] = 1.0
    out = separable_blur(img, gaussian_taps(1.0), wrap_cols=True)
    assert out[4, -1] > 0.09 and np.isclose(out.sum(), 1.0, atol=1e-6)
    assert separable_blur(img, gaussian_taps(1.0))[4, -1] == 0.0
