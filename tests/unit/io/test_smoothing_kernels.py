"""A volume's half-voxel Gaussian smoothing (:mod:`dsareg_engine.io.smoothing_kernels`) gives scipy's
``gaussian_filter`` values bit for bit, on every layout a volume comes in."""

import numpy as np
import pytest
from scipy import ndimage

from dsareg_engine.io.smoothing_kernels import SMOOTHED_SIGMA_VOX, smoothed


@pytest.mark.parametrize("order", ["C", "F"])
def test_the_values_are_scipys_on_grids_and_boxes_of_them(order):
    """Grids from one voxel to a few dozen per axis (the reflected ends of lines shorter than the kernel), HU-like
    values, whole and as a box (a head's crop: a strided view); C-ordered (NIfTI, MetaImage) and Fortran-ordered (a
    DICOM series) storage."""
    rng = np.random.default_rng(3 if order == "C" else 4)
    for _ in range(30):
        shape = tuple(int(n) for n in rng.integers(1, 30, 3))
        grid = np.asarray(rng.normal(60.0, 400.0, shape), np.float32, order=order)
        boxes = [grid]
        if min(shape) > 2:
            boxes.append(grid[1:-1, 1:, :-1])
        for voxels in boxes:
            expected = ndimage.gaussian_filter(voxels, SMOOTHED_SIGMA_VOX)
            got = smoothed(voxels, SMOOTHED_SIGMA_VOX)
            assert got.dtype == np.float32 and got.flags.c_contiguous
            assert np.array_equal(got, expected), f"{shape} {order}: {np.abs(got - expected).max()}"


def test_other_widths_and_types_are_scipys_own():
    """A width with another kernel radius, a float64 grid or a 2D image: scipy computes them (the same result)."""
    rng = np.random.default_rng(5)
    grid = rng.normal(0.0, 1.0, (9, 8, 7)).astype(np.float32)
    assert np.array_equal(smoothed(grid, 1.0), ndimage.gaussian_filter(grid, 1.0))
    assert np.array_equal(smoothed(grid.astype(np.float64), 0.5), ndimage.gaussian_filter(grid.astype(np.float64), 0.5))
    assert np.array_equal(smoothed(grid[0], 0.5), ndimage.gaussian_filter(grid[0], 0.5))


def test_it_smooths():
    """One bright voxel spreads to its neighbours with the normalised weights (the sum is kept)."""
    grid = np.zeros((7, 7, 7), np.float32)
    grid[3, 3, 3] = 1000.0
    out = smoothed(grid, SMOOTHED_SIGMA_VOX)
    assert 0 < out[3, 3, 3] < 1000.0 and out[3, 3, 4] > 0 and abs(float(out.sum()) - 1000.0) < 0.1
