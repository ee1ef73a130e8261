"""The medial measure's kernels (:mod:`dsareg_engine.io.medial_kernels`) give the values of the numpy / scipy
computations they replace: ``maximum_filter``'s cube maxima, the depth's shells, the nearer medial point, the
interpolation corners' agreement and ``cKDTree``'s ball counts (ties at the radius included)."""

import numpy as np
import pytest
from scipy import ndimage
from scipy.spatial import cKDTree

from dsareg_engine.io.medial_kernels import ball_counts, corner_agreement, maxima_at, nearer_marks, shell_depths
from dsareg_engine.io.medial_shape import _shell_table


def test_the_maxima_are_maximum_filters_at_the_chosen_voxels():
    """Grids from one voxel to a few dozen per axis (windows clipped at every face), the medial measure's int32
    depths and uint8 marks, a fifth to nearly all of the voxels chosen (runs along the last axis, with gaps; in C
    order as ``flatnonzero`` gives them, or shuffled), several sides."""
    rng = np.random.default_rng(7)
    for dtype in (np.int32, np.uint8):
        for _ in range(60):
            shape = tuple(int(n) for n in rng.integers(1, 16, 3))
            values = rng.integers(0, 60, shape).astype(dtype)
            index = np.flatnonzero(rng.random(values.size) < rng.choice([0.2, 0.5, 0.95]))
            if rng.random() < 0.3:  # any order: a run's columns are reused only where they hold
                index = rng.permutation(index)
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


def _nearest_squared(shape, index, targets):
    """Brute force: the squared distance from each flat ``index`` to the nearest of ``targets`` ``(M, 3)``."""
    voxels = np.stack(np.unravel_index(index, shape), axis=1)
    if len(targets) == 0:
        return np.full(len(voxels), np.inf)
    return ((voxels[:, None, :] - targets[None, :, :]) ** 2).sum(-1).min(1)


@pytest.mark.parametrize("max_r2", [4, 16, 64])
def test_the_depth_is_the_nearest_voxel_outside_the_mask_or_the_grid(max_r2):
    """Every inside voxel: the squared distance to the nearest voxel outside the mask, the grid's outside included
    (a ring of outside voxels around it), or −1 when that is beyond the table's longest offset."""
    rng = np.random.default_rng(max_r2)
    offsets, lengths = _shell_table(max_r2)
    for _ in range(40):
        shape = tuple(int(n) for n in rng.integers(1, 14, 3))
        inside = ndimage.binary_dilation(rng.random(shape) < rng.uniform(0.02, 0.5), iterations=int(rng.integers(0, 4)))
        index = np.flatnonzero(inside)
        padded = np.pad(inside, 1)
        outside = np.argwhere(~padded) - 1
        expected = _nearest_squared(shape, index, outside)
        expected = np.where(expected <= max_r2, expected, -1)
        assert np.array_equal(shell_depths(np.ascontiguousarray(inside), index, offsets, lengths), expected), shape


def test_deep_voxels_and_far_marks_read_as_the_brute_force():
    """A solid block with a few holes (depths past 7 voxels) and sparse marks (the nearest past 7 voxels away): the
    long offsets of the table, every value the brute force's."""
    rng = np.random.default_rng(21)
    offsets, lengths = _shell_table(100)
    inside = np.ones((20, 22, 24), bool)
    inside[tuple(rng.integers(0, 20, (3, 4)))] = False
    index = np.flatnonzero(inside)
    expected = _nearest_squared(inside.shape, index, np.argwhere(~np.pad(inside, 1)) - 1)
    assert expected.max() >= 49
    assert np.array_equal(shell_depths(inside, index, offsets, lengths), np.where(expected <= 100, expected, -1))
    marks = np.zeros((20, 22, 24), np.int8)
    marks[tuple(rng.integers(0, 20, (3, 6)))] = rng.integers(1, 3, 6)
    index = np.flatnonzero(np.ones(marks.shape, bool))
    to_plate = _nearest_squared(marks.shape, index, np.argwhere(marks == 1))
    to_tube = _nearest_squared(marks.shape, index, np.argwhere(marks == 2))
    expected = np.where(np.minimum(to_plate, to_tube) > 100, -1, (to_plate < to_tube).astype(int))
    assert np.minimum(to_plate, to_tube).max() >= 49
    assert np.array_equal(nearer_marks(marks, index, offsets, lengths), expected)


def test_a_voxel_is_plate_when_its_nearest_medial_point_is_a_plate_point_and_no_tube_point_is_as_near():
    """Random marks (plate 1, tube 2), every voxel: 1 when the nearest plate point is strictly nearer than every
    tube point (a voxel that is a point: its own mark), 0 when not, −1 when no mark lies within the table."""
    rng = np.random.default_rng(11)
    offsets, lengths = _shell_table(16)
    for _ in range(60):
        shape = tuple(int(n) for n in rng.integers(1, 14, 3))
        marks = np.where(rng.random(shape) < rng.uniform(0.0, 0.1), rng.integers(1, 3, shape), 0).astype(np.int8)
        index = np.flatnonzero(rng.random(marks.size) < 0.7)
        to_plate = _nearest_squared(shape, index, np.argwhere(marks == 1))
        to_tube = _nearest_squared(shape, index, np.argwhere(marks == 2))
        expected = np.where(np.minimum(to_plate, to_tube) > 16, -1, (to_plate < to_tube).astype(int))
        assert np.array_equal(nearer_marks(marks, index, offsets, lengths), expected), shape


def test_the_corners_agree_where_all_eight_are_equal():
    rng = np.random.default_rng(5)
    for _ in range(40):
        grid = (rng.random(tuple(int(n) for n in rng.integers(1, 9, 3))) < rng.uniform(0.1, 0.9)).astype(np.uint8)
        shape = tuple(int(n) for n in rng.integers(1, 12, 3))
        corners = [rng.integers(0, n, size) for n, size in zip(grid.shape, shape)]
        index = np.flatnonzero(np.ones(shape, bool))
        got = corner_agreement(grid, index, np.array(shape, np.int64), *[c.astype(np.int64) for c in corners])
        for n, flat in enumerate(index):
            i, j, k = np.unravel_index(flat, shape)
            block = grid[np.ix_(*[[c[x], min(c[x] + 1, size - 1)] for c, x, size in
                                  zip(corners, (i, j, k), grid.shape)])]
            assert got[n] == (1 if block.all() else 0 if not block.any() else -1)


def test_the_ball_counts_are_the_trees_counts_ties_at_the_radius_included():
    """``cKDTree.query_ball_point(..., return_length=True)`` over the inside voxels, at random radii and at radii
    whose square is an integer (voxels exactly at the radius: counted), balls cut by the grid's faces."""
    rng = np.random.default_rng(13)
    for _ in range(30):
        shape = tuple(int(n) for n in rng.integers(2, 30, 3))
        inside = rng.random(shape) < rng.uniform(0.05, 0.9)
        centres = np.argwhere(np.ones(shape, bool))[rng.integers(0, int(np.prod(shape)), 25)]
        radii = np.concatenate([rng.uniform(0.0, 12.0, 10), np.sqrt(rng.integers(0, 120, 10)),
                                rng.integers(0, 9, 5).astype(float)])
        tree = cKDTree(np.argwhere(inside))
        outer, half = ball_counts(inside, centres.astype(np.int64), radii, radii / 2.0)
        assert np.array_equal(outer, tree.query_ball_point(centres, radii, return_length=True)), shape
        assert np.array_equal(half, tree.query_ball_point(centres, radii / 2.0, return_length=True)), shape


def test_the_measure_is_the_same_with_and_without_the_kernels(monkeypatch):
    """A plate (a diploë), a tube beside and through it and a deep blob (depths beyond the kernels' shells), at an
    anisotropic voxel: the same plate share, medial points and plate voxels either way."""
    from dsareg_engine.io import medial_shape as module

    axis = np.arange(70) * 0.45
    x, y, z = np.meshgrid(axis, axis, axis[:50], indexing="ij")
    mask = np.abs(z - 6.0 - 0.1 * x) < 1.6  # a plate
    mask |= (y - 15.0) ** 2 + (z - 10.0) ** 2 < 1.3 ** 2  # a tube crossing it
    mask |= (x - 24.0) ** 2 + (y - 24.0) ** 2 + (z - 16.0) ** 2 < 7.0 ** 2  # a blob 15 working voxels deep
    shapes = []
    for here in (False, True):
        monkeypatch.setattr("dsareg_engine.io.volume_kernels.kernels_here", lambda here=here: here)
        shapes.append(module.medial_shape(mask, (0.45, 0.45, 0.5), with_parts=True))
    numpy_way, kernel_way = shapes
    assert numpy_way.plate.any() and (mask & ~numpy_way.plate).any()
    assert (numpy_way.plate_share, numpy_way.medial_points) == (kernel_way.plate_share, kernel_way.medial_points)
    assert np.array_equal(numpy_way.plate, kernel_way.plate)
