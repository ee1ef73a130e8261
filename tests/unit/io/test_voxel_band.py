"""The band test "within d mm of a mask" equals the full distance transform's: as a dilation by its ellipsoid, and
slab by slab in a box."""

import numpy as np
import pytest
from scipy import ndimage

from dsareg_engine.io import voxel_band
from dsareg_engine.io.voxel_band import within_mm

CASES = [  # shape, voxel mm per axis, band mm, share of mask voxels
    ((40, 46, 34), (0.3, 0.3, 0.3), 1.3, 0.001),
    ((30, 34, 40), (0.4, 0.4, 0.8), 1.8, 0.004),
    ((36, 30, 30), (0.5, 0.5, 0.5), 1.5, 0.0005),  # ties: 1.5 mm is 3 voxels exactly
    ((34, 30, 24), (0.3, 0.35, 0.6), 7.0, 0.0003),
    ((24, 24, 24), (1.0, 1.0, 1.0), 2.0, 0.3),
]


@pytest.mark.parametrize("shape, spacing, band, share", CASES)
@pytest.mark.parametrize("ball_rows, slab_voxels", [(0, 300), (0, 4000), (0, 10**7), (10**4, 10**7)])
def test_the_band_is_the_distance_transforms(monkeypatch, shape, spacing, band, share, ball_rows, slab_voxels):
    rng = np.random.default_rng(len(shape) + int(10 * band))
    mask = rng.random(shape) < share
    mask[:, :2] |= rng.random((shape[0], 2, shape[2])) < 0.5  # a plate along one face, as a skull
    monkeypatch.setattr(voxel_band, "MAX_BALL_ROWS", ball_rows)  # 0: slabs of distance transforms; else the ball
    monkeypatch.setattr(voxel_band, "SLAB_VOXELS", slab_voxels)
    expected = ndimage.distance_transform_edt(~mask, sampling=spacing) <= band
    assert np.array_equal(within_mm(mask, spacing, band), expected)


def test_an_empty_mask_has_an_empty_band():
    assert not within_mm(np.zeros((5, 6, 7), bool), (0.5, 0.5, 0.5), 2.0).any()


def test_a_single_voxels_band_is_its_ellipsoid():
    mask = np.zeros((21, 21, 11), bool)
    mask[10, 10, 5] = True
    band = within_mm(mask, (0.5, 0.5, 1.0), 2.0)
    i, j, k = np.indices(mask.shape)
    ellipsoid = ((i - 10) * 0.5) ** 2 + ((j - 10) * 0.5) ** 2 + ((k - 5) * 1.0) ** 2 <= 4.0
    assert np.array_equal(band, ellipsoid) and band.sum() == ellipsoid.sum() > 50


def test_a_bone_band_costs_a_few_bytes_per_voxel():
    """A skull-like shell's 1.3 mm band at 0.3 mm: the full distance transform peaks at ~60 bytes a voxel (an int32
    feature transform and float64 differences); the band a few (its row dilation, the result)."""
    import tracemalloc

    i, j, k = np.indices((120, 140, 130), dtype=np.float32)
    radius = np.sqrt(((i - 60) / 55) ** 2 + ((j - 70) / 65) ** 2 + ((k - 65) / 60) ** 2)
    shell = (radius > 0.9) & (radius < 0.95)
    del i, j, k, radius
    tracemalloc.start()
    band = within_mm(shell, (0.3, 0.3, 0.3), 1.3)
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    assert band.sum() > 2 * shell.sum()
    assert peak < 8 * shell.size, f"{peak / shell.size:.1f} bytes per voxel"  # measured 3.7; the transform 49


def test_a_wide_band_waits_for_a_compiling_helper_only_briefly(monkeypatch):
    """The transform's kernel group is waited for (a background helper may be compiling it) with the band's own
    limit: a submission's check reads volumes, and a frozen helper holds a read at most ``KERNEL_WAIT_S`` (the
    bounded wait itself, against a real SIGSTOPped holder: tests/unit/kernels/test_compile_lock.py)."""
    from dsareg_engine.io.volume_kernels import KERNEL_WAIT_S
    from dsareg_engine.kernels import compile_lock

    waits = []
    monkeypatch.setattr(compile_lock, "wait_for_group",
                        lambda name, wait_limit_s=None: waits.append((name, wait_limit_s)))
    mask = np.zeros((30, 30, 30), bool)
    mask[15, 15, 15] = True
    monkeypatch.setattr(voxel_band, "MAX_BALL_ROWS", 0)  # the slabs of distance transforms
    within_mm(mask, (0.5, 0.5, 0.5), 5.0)
    assert waits and set(waits) == {("volumes", KERNEL_WAIT_S)} and KERNEL_WAIT_S <= 30
