"""Which plate parts are bone: bone-sized and bone-placed (moved out of volume_vessels, issue 41)."""

import numpy as np
import pytest
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


@pytest.mark.parametrize("kernels", [False, True], ids=["numpy", "kernels"])
@pytest.mark.parametrize("bits", [16, 32])
def test_the_contact_share_is_that_of_the_index_lists(monkeypatch, kernels, bits):
    """Flat indices, a few voxels at a time (``GATHER_CHUNK``, small here), or the ``volumes`` group's kernel
    (:func:`dsareg_engine.io.medial_kernels.surface_contact`, where numba is loaded), on 16- and 32-bit labels: the
    reference's share."""
    from dsareg_engine.io import bone_plates as module

    monkeypatch.setattr(module, "GATHER_CHUNK", 7)
    monkeypatch.setattr("dsareg_engine.io.volume_kernels.kernels_here", lambda: kernels)
    rng = np.random.default_rng(4)
    for _ in range(60):
        shape = tuple(int(n) for n in rng.integers(1, 18, 3))
        labels, _ = ndimage.label(rng.random(shape) < 0.5, output=np.uint16 if bits == 16 else np.int32)
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


def _diploe_and_a_vessel():
    """A 30 x 30 x 2.5 mm diploë between two cortical tables (bone) and a 1-mm vessel running beside it, 0.5 mm
    voxels; the vessel passes 1 mm from the plate at one end (its rim) and is the largest tube."""
    spacing = np.array([0.5, 0.5, 0.5])
    mask = np.zeros((70, 70, 50), bool)
    mask[5:65, 5:65, 10:15] = True  # the diploë: 60 x 60 x 5 voxels
    bone = np.zeros(mask.shape, bool)
    bone[:, :, 9] = bone[:, :, 15] = True
    z, y = np.ogrid[:50, :70]
    tube = (z - 30) ** 2 + (y - 35) ** 2 <= 4  # radius 2 voxels, along the first axis
    mask[2:68] |= tube[None].transpose(0, 2, 1)
    return mask, bone, spacing


def test_a_reading_s_plates_are_found_and_its_tube_kept():
    from dsareg_engine.io.bone_plates import plates_found, without_plates

    mask, bone, spacing = _diploe_and_a_vessel()
    found = plates_found(mask, spacing, lambda box: bone[box])
    assert found.share is None and found.plates[20:50, 20:50, 11:14].all()  # the diploë's inside is set aside
    assert not (found.plates & ~mask).any()
    kept, share = without_plates(mask, found, "volume")
    assert share is None  # measure the kept mask again
    assert kept[10:60, 35, 30].all() and not kept[20:50, 20:50, 10:15].any()  # the vessel, not the plate


def test_a_mask_of_tubes_is_left_as_read():
    from dsareg_engine.io.bone_plates import plates_found, without_plates

    mask, bone, spacing = _diploe_and_a_vessel()
    mask[:, :, 10:15] = False  # the vessel alone
    found = plates_found(mask, spacing, lambda box: bone[box])
    assert not found.plates.any() and found.share is not None and found.share < 0.5
    kept, share = without_plates(mask, found, "volume")
    assert kept is mask and share == found.share
