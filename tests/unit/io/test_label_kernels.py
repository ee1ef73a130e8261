"""Connected components by runs (:mod:`dsareg_engine.io.label_kernels`) are ``scipy.ndimage.label``'s: the same
labels (face neighbours, numbered in the raster order of each component's first voxel), count and type."""

import numpy as np
import pytest
from scipy import ndimage

from dsareg_engine.io.label_kernels import MAX_RUN_SHARE, runs_labelled


@pytest.mark.parametrize("narrow", [False, True])
def test_the_labels_are_scipys(narrow, monkeypatch):
    """Random masks from sparse to nearly full, blobs and noise (every one taken, whatever its runs), grids of one
    voxel to a few dozen a side (runs at every face, U-shapes that join late in the raster), C and non-contiguous
    views."""
    from dsareg_engine.io import label_kernels

    monkeypatch.setattr(label_kernels, "MAX_RUN_SHARE", 1.0)
    rng = np.random.default_rng(17)
    for n in range(150):
        shape = tuple(int(s) for s in rng.integers(1, 30, 3))
        mask = rng.random(shape) < rng.uniform(0.02, 0.98)
        if n % 3 == 0:
            mask = ndimage.binary_opening(mask) | ndimage.binary_dilation(rng.random(shape) < 0.01, iterations=2)
        if n % 5 == 0 and min(shape) > 2:
            mask = mask[1:, ::-1, 1:]  # a view of another layout
        labels, count = runs_labelled(mask, narrow)
        expected, expected_count = ndimage.label(mask, output=np.uint16) if narrow else ndimage.label(mask)
        assert count == expected_count and labels.dtype == expected.dtype, (shape, n)
        assert np.array_equal(labels, expected), (shape, n)


def test_a_component_joined_late_keeps_its_first_voxels_number():
    """A U: two arms begun in separate rows (two provisional components) joined at the bottom, and a dot between
    them found after the left arm: the arms are one component numbered 1, the dot 2."""
    mask = np.zeros((4, 6, 7), bool)  # three empty planes: few runs a voxel
    mask[0, 0:5, 1] = mask[0, 0:5, 5] = True  # the arms
    mask[0, 5, 1:6] = True  # the bottom joins them
    mask[0, 2, 3] = True  # a dot between the arms
    labels, count = runs_labelled(mask)
    assert count == 2 and np.array_equal(labels, ndimage.label(mask)[0])
    assert labels[0, 0, 5] == 1 and labels[0, 2, 3] == 2


def test_more_components_than_16_bits_hold_take_32_bits():
    mask = np.zeros((6, 300, 600), bool)
    mask[0, ::2, ::2] = True  # 45,000 dots in the first plane
    mask[1, 1::2, 1::2] = True  # 45,000 more, touching none (diagonal only)
    got = runs_labelled(mask, narrow=True)
    assert got is not None
    labels, count = got
    assert count == 90_000 and labels.dtype == np.int32 and np.array_equal(labels, ndimage.label(mask)[0])


def test_a_noise_like_mask_is_left_to_scipy():
    mask = np.zeros((10, 10, 40), bool)
    mask[..., ::2] = True  # a run every other voxel: 0.5 runs a voxel
    assert 0.5 > MAX_RUN_SHARE and runs_labelled(mask) is None


def test_component_runs_size_mark_and_write_as_the_label_grid_does(monkeypatch):
    """Without a label grid: each component's size is ``label_sizes``', the components touching a second mask are
    those its labels there name, and the chosen components are written as ``map_labels`` writes them — into a
    whole grid and into a box of a larger one; random masks, C and non-contiguous views."""
    from dsareg_engine.io import label_kernels
    from dsareg_engine.io.label_kernels import component_runs
    from dsareg_engine.io.voxel_steps import label_sizes

    monkeypatch.setattr(label_kernels, "MAX_RUN_SHARE", 1.0)
    rng = np.random.default_rng(23)
    for n in range(80):
        shape = tuple(int(s) for s in rng.integers(1, 24, 3))
        mask = rng.random(shape) < rng.uniform(0.05, 0.9)
        if n % 4 == 0 and min(shape) > 2:
            mask = mask[1:, ::-1, 1:]
        near = rng.random(mask.shape) < 0.05
        labels, count = ndimage.label(mask)
        found = component_runs(mask)
        assert found.count == count, (shape, n)
        assert np.array_equal(found.sizes(), label_sizes(labels, count)), (shape, n)
        expected_touching = np.bincount(labels[near], minlength=count + 1) > 0
        assert np.array_equal(found.touching(near)[1:], expected_touching[1:]), (shape, n)
        chosen = rng.random(count + 1) < 0.5
        chosen[0] = False
        whole = np.zeros(mask.shape, bool)
        found.write(whole, chosen)
        assert np.array_equal(whole, chosen[labels]), (shape, n)
        larger = np.zeros(tuple(s + 2 for s in mask.shape), bool)
        found.write(larger[1:-1, 1:-1, 1:-1], chosen)
        assert np.array_equal(larger[1:-1, 1:-1, 1:-1], chosen[labels]) and larger.sum() == whole.sum(), (shape, n)


def test_component_runs_leave_a_noise_like_mask_to_scipy():
    from dsareg_engine.io.label_kernels import component_runs

    mask = np.zeros((10, 10, 40), bool)
    mask[..., ::2] = True
    assert component_runs(mask) is None
