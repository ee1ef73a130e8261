"""Which plate parts are bone: bone-sized and bone-placed (moved out of volume_vessels, issue 41)."""

import numpy as np
from scipy import ndimage

from dsareg_engine.io.bone_plates import PLATE_PART_MM3, bone_contact, bone_plates


def _contact_by_index_lists(labels, index, box, bone):
    """The reference: the part's voxels as index triples, each neighbour clipped to the grid (before issue 41)."""
    inside = np.nonzero(labels[box] == index)
    voxels = [i + s.start for i, s in zip(inside, box)]
    surface = np.zeros(len(voxels[0]), bool)
    touching = np.zeros(len(voxels[0]), bool)
    for axis in range(3):
        for step in (-1, 1):
            neighbour = list(voxels)
            neighbour[axis] = np.clip(voxels[axis] + step, 0, labels.shape[axis] - 1)
            outside = labels[tuple(neighbour)] != index
            surface |= outside
            touching |= outside & bone[tuple(neighbour)]
    return float(touching.sum() / max(int(surface.sum()), 1))


def test_the_contact_share_is_that_of_the_index_lists(monkeypatch):
    """Flat indices, a few voxels at a time (``GATHER_CHUNK``, small here): the reference's share."""
    from dsareg_engine.io import bone_plates as module

    monkeypatch.setattr(module, "GATHER_CHUNK", 7)
    rng = np.random.default_rng(4)
    for _ in range(60):
        shape = tuple(int(n) for n in rng.integers(1, 18, 3))
        labels, _ = ndimage.label(rng.random(shape) < 0.5)
        bone = rng.random(shape) < 0.3
        for index, box in enumerate(ndimage.find_objects(labels), start=1):
            assert bone_contact(labels, index, box, bone) == _contact_by_index_lists(labels, index, box, bone)


def test_a_large_plate_against_bone_is_bone_and_one_in_tissue_or_a_small_one_is_not():
    spacing = np.array([0.5, 0.5, 0.5])
    plate = np.zeros((60, 60, 40), bool)
    plate[5:55, 5:25, 10:14] = True  # 50 x 20 x 4 voxels: 500 mm³, between two cortical tables
    plate[5:55, 35:55, 25:29] = True  # the same in tissue
    plate[28:31, 28:31, 32:35] = True  # 27 voxels: 3.4 mm³, against bone
    bone = np.zeros(plate.shape, bool)
    bone[:, :30, 9] = bone[:, :30, 14] = True
    bone[25:34, 25:34, 31] = True
    assert 50 * 20 * 4 * 0.125 >= PLATE_PART_MM3
    found = bone_plates(plate, spacing, lambda box: bone[box])
    assert found[5:55, 5:25, 10:14].all()
    assert not found[5:55, 35:55, 25:29].any() and not found[28:31, 28:31, 32:35].any()
