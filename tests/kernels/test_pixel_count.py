"""The hot-pixel filter's counting kernel against its numpy twin: the same drops, counts, largest count and number
dropped, chunk after chunk, with and without flagged pixels."""
import numpy as np
import pytest

from ti_cmax.kernels.pixel_count import PixelCounter, count_pixels_numpy


@pytest.mark.parametrize("flag_share", [0.0, 0.02, 1.0])
def test_counter_matches_numpy_twin(ti_runtime, flag_share):
    rng = np.random.default_rng(5)
    width, height = 37, 23
    counts, twin = np.zeros(width * height, np.int32), np.zeros(width * height, np.int32)
    flagged = (rng.random(width * height) < flag_share).astype(np.int8)
    counter = PixelCounter(width, height, counts, flagged, capacity=3000)
    for n in (1, 2999, 3000, 0, 517):
        x = rng.integers(0, width, n).astype(np.uint16)
        y = rng.integers(0, height, n).astype(np.uint16)
        keep, peak, dropped = counter(x, y)
        keep_twin, peak_twin, dropped_twin = count_pixels_numpy(x, y, width, flagged, twin)
        np.testing.assert_array_equal(np.ones(n, bool) if keep is None else keep, keep_twin)
        assert (keep is None) == (dropped == 0)
        assert (peak, dropped) == (peak_twin, dropped_twin)
        np.testing.assert_array_equal(counts, twin)
    assert counts.sum() == twin.sum() > 0 or flag_share == 1.0


def test_counter_without_flags_counts_every_event_and_refuses_pixels_off_the_sensor(ti_runtime):
    width, height = 8, 4
    counts, flagged = np.zeros(width * height, np.int32), np.ones(width * height, np.int8)
    counter = PixelCounter(width, height, counts, flagged, capacity=10)
    keep, peak, dropped = counter(np.array([1, 1, 7, 1], np.uint16), np.array([0, 0, 3, 0], np.uint16),
                                  any_flagged=False)
    assert keep is None and (peak, dropped) == (3, 0)
    assert counts[1] == 3 and counts[3 * width + 7] == 1 and counts.sum() == 4
    with pytest.raises(ValueError, match="at most 10"):
        counter(np.zeros(11, np.uint16), np.zeros(11, np.uint16))
    for x, y in ((8, 0), (0, 4)):
        with pytest.raises(ValueError, match="1 events off the 8 x 4 sensor"):
            counter(np.array([0, x], np.uint16), np.array([0, y], np.uint16), any_flagged=False)
