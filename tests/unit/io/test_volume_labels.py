"""Label maps and multi-piece masks read as vessels, on volumes made here (tubes along the grid's axes)."""

import numpy as np
import pytest

from dsareg_engine.errors import DsaregInputError
from dsareg_engine.io.volume_io import Volume
from dsareg_engine.io.volume_kind import VolumeReading
from dsareg_engine.io.volume_labels import label_map
from dsareg_engine.io.volume_vessels import extract_vessels

SHAPE = (60, 48, 48)
SPACING = 0.4


def _tube(grid, axis: int, centre: tuple[float, float], radius: float, span: tuple[int, int]) -> np.ndarray:
    """A tube (voxel units) along ``axis`` through ``centre`` (the two other axes), from ``span[0]`` to ``span[1]``."""
    others = [a for a in range(3) if a != axis]
    inside = (grid[others[0]] - centre[0]) ** 2 + (grid[others[1]] - centre[1]) ** 2 <= radius**2
    return inside & (grid[axis] >= span[0]) & (grid[axis] < span[1])


@pytest.fixture(scope="module")
def grid():
    return np.indices(SHAPE)


def _volume(voxels: np.ndarray) -> Volume:
    return Volume(voxels.astype(np.float32), np.diag([SPACING, SPACING, SPACING, 1.0]), "nifti")


def _kept_share(extraction, labelled: np.ndarray) -> float:
    return float((extraction.kept & labelled).sum() / labelled.sum())


def test_every_label_above_zero_is_vessel(grid):
    """TopCoW-like: a large label (ICA) and thin ones (basilar 1, PCA 2); intensity windows dropped 1 and 2."""
    labels = np.zeros(SHAPE, np.uint8)
    labels[_tube(grid, 0, (24, 24), 4.0, (4, 56))] = 4
    labels[_tube(grid, 1, (30, 10), 1.6, (4, 44))] = 1
    labels[_tube(grid, 2, (12, 36), 1.6, (4, 44))] = 2
    labels[_tube(grid, 1, (45, 38), 2.0, (4, 44))] = 3
    extraction = extract_vessels(_volume(labels))
    readout = extraction.readout
    assert readout.kind == "labels" and readout.labels == [1, 2, 3, 4]
    assert _kept_share(extraction, labels > 0) >= 0.95
    for label in (1, 2):
        assert _kept_share(extraction, labels == label) >= 0.95
    assert "labels 1, 2, 3, 4" in readout.text() and "and up" not in readout.text()
    whats = {decision.what: decision for decision in readout.decisions}
    assert whats["vessel labels"].chosen == "labels 1, 2, 3, 4" and whats["vessel labels"].source == "measured"
    assert extraction.mesh.n_faces > 0


def test_volume_labels_choose_and_are_checked(grid):
    labels = np.zeros(SHAPE, np.uint8)
    labels[_tube(grid, 0, (24, 24), 4.0, (4, 56))] = 4
    labels[_tube(grid, 1, (30, 10), 1.6, (4, 44))] = 1
    extraction = extract_vessels(_volume(labels), VolumeReading(labels=(4,)))
    assert extraction.readout.labels == [4] and not (extraction.kept & (labels == 1)).any()
    assert {d.what: d for d in extraction.readout.decisions}["vessel labels"].source == "option"
    with pytest.raises(DsaregInputError, match="holds none of the labels \\[9\\]; it holds 1, 4"):
        extract_vessels(_volume(labels), VolumeReading(labels=(9,)))
    image = np.random.default_rng(0).normal(100.0, 20.0, SHAPE)
    with pytest.raises(DsaregInputError, match="not a label map") as refused:
        label_map(image.astype(np.float32), VolumeReading(labels=(1,)))
    assert refused.value.field == "volume"
    with pytest.raises(DsaregInputError) as bad:
        VolumeReading(labels=(0, 2))
    assert bad.value.field == "options.volume_labels"


def test_a_mask_in_pieces_keeps_every_piece_but_specks(grid):
    """A 0/1 mask whose tree is cut in pieces (small ones below 5 % of the largest): all are vessels."""
    mask = _tube(grid, 0, (24, 24), 4.0, (2, 58))
    for centre in ((8, 8), (40, 8), (8, 40), (40, 40)):
        mask |= _tube(grid, 0, centre, 1.2, (20, 36))  # 4 pieces of ~70 voxels: ~2.5 % of the trunk each
    speck = np.zeros(SHAPE, bool)
    speck[50, 44, 44] = speck[50, 44, 45] = True
    extraction = extract_vessels(_volume(mask | speck))
    readout = extraction.readout
    assert _kept_share(extraction, mask) >= 0.95 and not (extraction.kept & speck).any()
    assert readout.window() == "labels 1" and readout.components == 5
    pieces = {d.what: d for d in readout.decisions}["vessel pieces"]
    assert pieces.chosen == "5 of 6 pieces" and pieces.measure >= 0.95


def test_images_are_not_label_maps(grid):
    image = np.random.default_rng(1).integers(0, 255, SHAPE).astype(np.float32)  # 8-bit, whole values: an image
    assert label_map(image, VolumeReading()) is None
    two_levels = np.where(_tube(grid, 0, (24, 24), 4.0, (2, 58)), 300.0, 40.0)  # no background of 0
    assert label_map(two_levels, VolumeReading()) is None
    assert label_map(np.where(two_levels > 100, 1.0, 0.0), VolumeReading(kind="cta")) is None  # a kind given
    quantized = np.round(8.0 * np.clip(4.5 - np.hypot(grid[1] - 24.0, grid[2] - 24.0), 0, 1)) * 100.0
    assert len(np.unique(quantized)) > 3 and label_map(quantized, VolumeReading()) is None  # partial volume, 100-800
    assert label_map(np.where(two_levels > 100, 255.0, 0.0), VolumeReading()).present == (255,)  # a 0/255 mask
