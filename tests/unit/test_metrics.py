"""Tests of dsareg_engine/metrics.py."""

import numpy as np
import pytest

from dsareg_engine.metrics import within_px


def _brute_force_within(mask: np.ndarray, tolerance_px: float) -> np.ndarray:
    """Every pixel centre's distance to every mask pixel centre, by hand: the independent answer."""
    rows, cols = np.nonzero(mask)
    yy, xx = np.mgrid[0:mask.shape[0], 0:mask.shape[1]]
    if rows.size == 0:
        return np.zeros(mask.shape, bool)
    squared = (yy[..., None] - rows) ** 2 + (xx[..., None] - cols) ** 2
    return squared.min(axis=-1) <= tolerance_px ** 2


@pytest.mark.parametrize("tolerance_px", [0.0, 0.5, 1.0, 1.5, 2.0, np.sqrt(5.0), 2.5, 3.0, 4.2])
@pytest.mark.parametrize("density", [0.0, 0.002, 0.03, 0.3])
def test_within_px_is_the_set_of_pixels_within_the_euclidean_tolerance(tolerance_px, density):
    rng = np.random.default_rng(int(1000 * tolerance_px) + int(1000 * density))
    mask = rng.random((37, 41)) < density
    mask[0, 5] = density > 0  # a pixel on the image's edge: nothing beyond the edge may count
    assert np.array_equal(within_px(mask, tolerance_px), _brute_force_within(mask, tolerance_px))


def test_within_px_of_a_single_pixel_at_two_px_is_the_13_pixel_disc():
    mask = np.zeros((9, 9), bool)
    mask[4, 4] = True
    near = within_px(mask, 2.0)
    assert near.sum() == 13  # (0,0), 4 at 1, 4 at sqrt(2), 4 at 2; not (1,2) at sqrt(5)
    assert near[4, 6] and near[2, 4] and not near[5, 6] and not near[6, 6]


def test_within_px_of_a_negative_tolerance_is_nothing():
    assert not within_px(np.ones((4, 4), bool), -1.0).any()
