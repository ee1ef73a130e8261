"""How far a piece runs with its lumen against bone (issue 41: dural venous sinuses in a CTA)."""

import numpy as np
import pytest

from dsareg_engine.io.venous_sinuses import SINUS_RADIUS_MM, TOUCH_MM, along_bone
from dsareg_engine.io.voxel_steps import grown


def _tube_by_a_wall(spacing, gap_mm: float, wall_length_share: float = 1.0, radius_mm: float = 3.0):
    """A straight tube (axis along the grid's first axis, 60 mm long) of ``radius_mm`` whose lumen lies ``gap_mm``
    from a flat wall of bone (the plane below it in the second axis) over ``wall_length_share`` of its length: the
    piece, and its voxels with a face neighbour in bone."""
    shape = np.round(np.array([70.0, 24.0, 24.0]) / spacing).astype(int)
    z, y, x = (np.arange(n) * s for n, s in zip(shape, spacing))
    z, y, x = z[:, None, None], y[None, :, None], x[None, None, :]
    wall_y = 4.0
    centre_y = wall_y + gap_mm + radius_mm
    piece = ((y - centre_y) ** 2 + (x - 12.0) ** 2 <= radius_mm ** 2) & (z >= 5.0) & (z < 65.0)
    bone = (y < wall_y) & (z < 5.0 + 60.0 * wall_length_share) & np.ones(shape, bool)
    return piece, piece & grown(bone)


@pytest.mark.parametrize("spacing", [(0.5, 0.5, 0.5), (1.0, 0.45, 0.45)])
def test_a_tube_against_bone_along_its_length_reads_one_and_its_radius(spacing):
    spacing = np.asarray(spacing)
    piece, touching = _tube_by_a_wall(spacing, gap_mm=0.0)
    measure = along_bone(piece, spacing, touching)
    assert measure.share > 0.9 and measure.sinus
    assert abs(measure.radius_mm - 3.0) < 0.75  # the medial depth, in mm at any voxel


def test_a_tube_apart_from_bone_or_along_part_of_it():
    spacing = np.full(3, 0.5)
    piece, touching = _tube_by_a_wall(spacing, gap_mm=3.0 + TOUCH_MM)  # CSF between: no contact at all
    assert not touching.any() and along_bone(piece, spacing, touching).share == 0.0
    piece, touching = _tube_by_a_wall(spacing, gap_mm=0.0, wall_length_share=0.4)  # a canal for 40 % of its length
    assert 0.3 < along_bone(piece, spacing, touching).share < 0.55
    piece, touching = _tube_by_a_wall(spacing, gap_mm=0.0, radius_mm=1.0)  # a vessel's width: along bone, no sinus
    thin = along_bone(piece, spacing, touching)
    assert thin.share > 0.9 and thin.radius_mm < SINUS_RADIUS_MM and not thin.sinus
