"""Morphology by shifted slices gives scipy.ndimage's results (issue 41: the whole-head CTA's boxes)."""

import numpy as np
import pytest
from scipy import ndimage

from dsareg_engine.io.voxel_steps import bounding_box, cube_maximum, cube_minimum, grown


@pytest.fixture(params=[False, True], ids=["numpy", "kernels"])
def kernels(request, monkeypatch):
    """Both ways of the steps: numpy / scipy, and the ``volumes`` group's kernels where numba is loaded
    (:mod:`dsareg_engine.io.voxel_kernels`, :mod:`dsareg_engine.io.label_kernels`)."""
    monkeypatch.setattr("dsareg_engine.io.volume_kernels.kernels_here", lambda: request.param)
    return request.param


def _masks(count, seed):
    rng = np.random.default_rng(seed)
    for _ in range(count):
        shape = tuple(int(n) for n in rng.integers(1, 18, 3))
        yield rng, rng.random(shape) < rng.uniform(0.0, 0.3)


@pytest.mark.parametrize("steps", [1, 2, 5])
def test_grown_is_binary_dilation_with_its_cross(steps, kernels):
    for rng, mask in _masks(60, steps):
        assert np.array_equal(grown(mask, steps), ndimage.binary_dilation(mask, iterations=steps))
        within = rng.random(mask.shape) < 0.6
        assert np.array_equal(grown(mask, steps, within), ndimage.binary_dilation(mask, iterations=steps, mask=within))


@pytest.mark.parametrize("size", [1, 3, 5, 9])
def test_a_cube_extreme_is_the_reflecting_filter(size):
    for rng, mask in _masks(60, size):
        values = rng.integers(0, 50, mask.shape).astype(np.int32)
        assert np.array_equal(cube_maximum(values, size), ndimage.maximum_filter(values, size=size))
        assert np.array_equal(cube_minimum(values, size), ndimage.minimum_filter(values, size=size))
        assert np.array_equal(cube_minimum(mask, size), ndimage.minimum_filter(mask, size=size))
        expected, temporary = ndimage.minimum_filter(mask, size=size), mask.copy()
        assert cube_minimum(temporary, size, in_place=True) is temporary and np.array_equal(temporary, expected)
        assert np.array_equal(cube_maximum(mask.view(np.uint8), size),
                              ndimage.maximum_filter(mask.view(np.uint8), size=size, mode="constant"))


def test_an_even_cube_is_refused():
    with pytest.raises(ValueError):
        cube_maximum(np.zeros((3, 3, 3)), 4)


def test_shifted_slices_are_much_cheaper_than_the_neighbourhood_loops():
    """The reason for the module: one dilation step and a 5-voxel maximum of a 16 M voxel grid, CPU s."""
    import time

    mask = np.zeros((256, 256, 256), bool)
    mask[40:200, 40:200, 120:126] = True
    start = time.process_time()
    ours = grown(mask)
    mine = time.process_time() - start
    start = time.process_time()
    theirs = ndimage.binary_dilation(mask)
    assert np.array_equal(ours, theirs) and mine < 0.5 * (time.process_time() - start)


def test_the_bounding_box_is_that_of_the_voxels_grown_and_clipped():
    from dsareg_engine.io.voxel_steps import bounding_box

    for _, mask in _masks(40, 11):
        hits = np.argwhere(mask)
        box = bounding_box(mask, 2)
        if len(hits) == 0:
            assert box is None
            continue
        low, high = np.maximum(hits.min(0) - 2, 0), np.minimum(hits.max(0) + 3, mask.shape)
        assert box == tuple(slice(int(a), int(b)) for a, b in zip(low, high))


def test_label_sizes_are_the_counts_without_a_64_bit_copy_of_the_grid(monkeypatch):
    """Issue 41: ``np.bincount`` of a whole label grid holds it as 64-bit integers (400 MB for a skull's box)."""
    import tracemalloc

    from dsareg_engine.io import voxel_steps
    from dsareg_engine.io.voxel_steps import label_sizes

    for slab in (1 << 22, 7):  # 7: a plane at a time (and several slabs)
        monkeypatch.setattr(voxel_steps, "LABEL_SLAB", slab)
        for rng, mask in _masks(30, 5):
            labels, count = ndimage.label(mask)
            expected = np.bincount(labels.ravel(), minlength=count + 1)
            assert np.array_equal(label_sizes(labels, count), expected)
            assert np.array_equal(label_sizes(labels, count, mask), expected)  # counted on the mask's voxels
    monkeypatch.setattr(voxel_steps, "LABEL_SLAB", 1 << 16)
    labels, count = ndimage.label(np.random.default_rng(0).random((128, 128, 128)) < 0.3)
    tracemalloc.start()
    sizes = label_sizes(labels, count)
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    assert sizes.sum() == labels.size and peak < 2 * labels.nbytes / 4, (peak, labels.nbytes)


def test_labels_are_scipy_s_in_16_bits_where_they_fit_and_32_where_not(monkeypatch, kernels):
    """Issue 41: a 600-slice head's box labelled in 16 bits (2 bytes a voxel, not 4); over 65,535 components, or a
    grid below ``LABEL16_VOXELS`` (16 bits label ~30 % slower): 32."""
    from dsareg_engine.io import voxel_steps
    from dsareg_engine.io.voxel_steps import labelled

    mask = next(_masks(1, 7))[1]
    assert labelled(mask)[0].dtype == np.int32  # a small grid
    assert labelled(mask, narrow_above=0)[0].dtype == np.uint16  # asked for (a caller at its memory peak)
    monkeypatch.setattr(voxel_steps, "LABEL16_VOXELS", 0)
    for rng, mask in _masks(30, 7):
        labels, count = labelled(mask)
        expected, expected_count = ndimage.label(mask)
        assert labels.dtype == np.uint16 and count == expected_count and np.array_equal(labels, expected)
    sparse = np.zeros((82, 82, 82), bool)
    sparse[::2, ::2, ::2] = True  # 68,921 single voxels
    labels, count = labelled(sparse)
    assert count == 41 ** 3 and labels.dtype == np.int32 and np.array_equal(labels, ndimage.label(sparse)[0])


def test_labels_are_mapped_into_a_box_a_slab_at_a_time(monkeypatch, kernels):
    """``map_labels`` writes ``table[labels]`` into a box of a larger grid, slab by slab (``MAP_CHUNK``)."""
    from dsareg_engine.io import voxel_steps
    from dsareg_engine.io.voxel_steps import labelled, map_labels

    for chunk in (5, 1 << 23):
        monkeypatch.setattr(voxel_steps, "MAP_CHUNK", chunk)
        for rng, mask in _masks(20, 9):
            labels, count = labelled(mask)
            table = rng.random(count + 1) < 0.5
            out = np.zeros(tuple(n + 3 for n in mask.shape), bool)
            box = tuple(slice(1, 1 + n) for n in mask.shape)
            map_labels(out[box], table, labels)
            expected = np.zeros(out.shape, bool)
            expected[box] = table[labels]
            assert np.array_equal(out, expected)


@pytest.mark.parametrize("shape", [(40, 37), (1, 9), (18, 21, 16), (1, 12, 14), (9, 1, 11)])
def test_filled_holes_are_scipys(shape, kernels):
    """One labelling of the background gives what ``binary_fill_holes``' repeated dilation gives: random masks
    (holes, cavities, pockets open at a face), shells, and the empty and full grids."""
    from dsareg_engine.io.voxel_steps import filled_holes

    rng = np.random.default_rng(sum(shape))
    cases = [rng.random(shape) < share for share in (0.2, 0.45, 0.6, 0.8)]
    cases += [np.zeros(shape, bool), np.ones(shape, bool)]
    shell = np.zeros(shape, bool)
    inner = tuple(slice(1, max(n - 1, 1)) for n in shape)
    shell[inner] = True
    shell[tuple(slice(2, max(n - 2, 2)) for n in shape)] = False  # a closed shell: its inside is a hole
    cases.append(shell)
    for mask in cases:
        assert np.array_equal(filled_holes(mask), ndimage.binary_fill_holes(mask))
    assert filled_holes(shell).sum() >= shell.sum()


def test_a_closing_by_grown_steps_is_scipys_away_from_the_faces(kernels):
    """The MRA head mask's closing (``_head_mask``): ``~grown(~grown(x, n), n)`` on a grid padded by ``n`` is
    ``binary_closing(x, iterations=n)`` on every voxel of the unpadded grid (scipy erodes from the faces, which the
    padding takes)."""
    rng = np.random.default_rng(7)
    for _ in range(30):
        shape = tuple(int(n) for n in rng.integers(1, 20, 3))
        mask = ndimage.gaussian_filter(rng.random(shape), 1.5) > rng.uniform(0.45, 0.55)
        for pad in (1, 2, 3):
            padded = np.pad(mask, pad, mode="edge")
            inner = (slice(pad, -pad),) * 3
            expected = ndimage.binary_closing(padded, iterations=pad)[inner]
            assert np.array_equal((~grown(~grown(padded, pad), pad))[inner], expected)


def test_components_answer_alike_from_runs_and_from_a_label_grid(monkeypatch):
    """``components``: by runs where the volume kernels are in use, else a label grid: the same count, sizes,
    contact and written components."""
    from dsareg_engine.io import volume_kernels
    from dsareg_engine.io.label_kernels import ComponentRuns
    from dsareg_engine.io.voxel_steps import LabelledComponents, components

    rng = np.random.default_rng(41)
    for n in range(20):
        shape = tuple(int(s) for s in rng.integers(2, 20, 3))
        mask = ndimage.binary_opening(rng.random(shape) < 0.5) | (rng.random(shape) < 0.02)
        near, chosen = rng.random(shape) < 0.05, None
        answers = []
        for in_use, kind in ((True, ComponentRuns), (False, LabelledComponents)):
            monkeypatch.setattr(volume_kernels, "kernels_in_use", lambda in_use=in_use: in_use)
            found = components(mask)
            assert isinstance(found, kind), (n, kind)
            if chosen is None:
                chosen = rng.random(found.count + 1) < 0.5
                chosen[0] = False  # the background is never chosen
            out = np.zeros(shape, bool)
            found.write(out, chosen)
            answers.append((found.count, found.sizes(), found.touching(near), out))
        (count_a, sizes_a, touch_a, out_a), (count_b, sizes_b, touch_b, out_b) = answers
        assert count_a == count_b and np.array_equal(sizes_a, sizes_b), n
        assert np.array_equal(touch_a[1:], touch_b[1:]) and np.array_equal(out_a, out_b), n
