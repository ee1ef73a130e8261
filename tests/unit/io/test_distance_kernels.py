"""The separable squared distance transform equals scipy's distances (issue 41: a TOF slab's 7-mm scalp band)."""

import numpy as np
import pytest
from scipy import ndimage

from dsareg_engine.io.distance_kernels import squared_distances


def _transform(mask, spacing):
    out = np.empty(mask.shape)
    squared_distances(mask, *map(float, spacing), out)
    return out


@pytest.mark.parametrize("spacing", [(1.0, 1.0, 1.0), (0.5, 0.5, 0.5), (0.35, 0.35, 0.3), (0.4, 0.4, 0.8),
                                     (0.3, 0.45, 0.6)])
def test_the_distances_are_scipys(spacing):
    """Random masks from sparse to dense, on grids from one voxel thin to a few dozen: the float64 values of
    ``(feature - index) × spacing`` squared and summed over the axes in order (scipy's distance, squared); the same
    bits but where a voxel is exactly as far from two mask voxels (3-4-5 offsets) and the two sums round apart."""
    rng = np.random.default_rng(int(100 * sum(spacing)))
    for _ in range(40):
        shape = tuple(int(n) for n in rng.integers(1, 24, 3))
        mask = rng.random(shape) < rng.choice([0.002, 0.02, 0.2, 0.7])
        if not mask.any():
            mask[tuple(int(rng.integers(n)) for n in shape)] = True
        features = ndimage.distance_transform_edt(~mask, sampling=spacing, return_distances=False, return_indices=True)
        expected = np.zeros(shape)
        for axis in range(3):
            index = np.arange(shape[axis]).reshape([-1 if b == axis else 1 for b in range(3)])
            expected += ((features[axis] - index).astype(np.float64) * spacing[axis]) ** 2
        got = _transform(mask, spacing)
        assert np.allclose(got, expected, rtol=4e-16, atol=0)
        assert (got == expected).mean() > 0.99


def test_an_empty_mask_is_infinitely_far_and_a_full_one_is_zero():
    assert np.isinf(_transform(np.zeros((3, 4, 5), bool), (0.5, 0.5, 0.5))).all()
    assert (_transform(np.ones((3, 4, 5), bool), (0.5, 0.5, 0.5)) == 0).all()


def test_a_single_voxel_gives_its_ellipsoidal_distances():
    mask = np.zeros((9, 11, 7), bool)
    mask[4, 2, 6] = True
    i, j, k = np.indices(mask.shape)
    expected = ((i - 4) * 0.4) ** 2 + ((j - 2) * 0.4) ** 2 + ((k - 6) * 0.9) ** 2
    assert np.allclose(_transform(mask, (0.4, 0.4, 0.9)), expected, rtol=1e-15, atol=0)
