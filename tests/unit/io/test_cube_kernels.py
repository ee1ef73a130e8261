"""The cube maxima at chosen voxels (:mod:`dsareg_engine.io.cube_kernels`) are ``maximum_filter``'s values there."""

import numpy as np
from scipy import ndimage

from dsareg_engine.io.cube_kernels import maxima_at


def test_the_maxima_are_maximum_filters_at_the_chosen_voxels():
    """Grids from one voxel to a few dozen per axis (windows clipped at every face), the medial measure's int32
    depths and uint8 marks, half the voxels chosen (in C order, as ``flatnonzero`` gives them), several sides."""
    rng = np.random.default_rng(7)
    for dtype in (np.int32, np.uint8):
        for _ in range(25):
            shape = tuple(int(n) for n in rng.integers(1, 16, 3))
            values = rng.integers(0, 60, shape).astype(dtype)
            index = np.flatnonzero(rng.random(values.size) < 0.5)
            for outer, inner in ((2, 1), (1, 1), (3, 0), (2, 2)):
                got_outer, got_inner = maxima_at(values, index, outer, inner)
                for side, got in ((outer, got_outer), (inner, got_inner)):
                    expected = ndimage.maximum_filter(values, size=2 * side + 1, mode="reflect").ravel()[index]
                    assert got.dtype == values.dtype and np.array_equal(got, expected), (shape, side)


def test_a_peak_reaches_its_cube_only():
    values = np.zeros((9, 9, 9), np.int32)
    values[4, 4, 4] = 25
    index = np.flatnonzero(np.ones(values.size, bool))
    outer, inner = maxima_at(values, index, 2, 1)
    near = np.zeros(values.shape, bool)
    near[2:7, 2:7, 2:7] = True
    assert np.array_equal(outer.reshape(values.shape) == 25, near)
    assert int((inner == 25).sum()) == 27
