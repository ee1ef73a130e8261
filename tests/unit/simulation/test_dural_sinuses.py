"""The generator's dural sinuses: against the inner table, apart from the tree, the size of real ones."""

import numpy as np
import pytest
from scipy import ndimage

from dsareg_engine.simulation.dural_sinuses import HEIGHT_MM, SINUS_MM, dural_sinuses
from dsareg_engine.simulation.synthetic_heads_layered import _grid, _skull
from dsareg_engine.simulation.synthetic_volumes import vessel_tree


@pytest.mark.parametrize("section", ["triangle", "round"])
def test_the_sinuses_lie_against_the_inner_table_apart_from_the_tree(section):
    tree = vessel_tree(2, 3)
    spacing = np.full(3, 0.5)
    axes, depth, _, occupancy, _ = _grid(tree, spacing, (30.0, 30.0, 40.0))
    centre, inner = _skull(tree, (30.0, 30.0, 40.0))
    veins = dural_sinuses(axes, depth, centre, inner, section)
    assert ndimage.label(veins)[1] == 1  # one venous system: the sagittal sinus meets the transverse at the torcula
    assert np.all(depth[veins] < 0) and np.all(depth[veins] >= -HEIGHT_MM)  # inside, under the table
    assert np.count_nonzero(veins & (depth >= -1.0)) > 0.05 * veins.sum()  # on the table along its course
    assert not (ndimage.binary_dilation(veins, iterations=8) & (occupancy > 0)).any()  # 4 mm or more from the tree
    x = np.broadcast_to(axes[0], depth.shape)[veins]
    y = np.broadcast_to(axes[1], depth.shape)[veins]
    z = np.broadcast_to(axes[2], depth.shape)[veins]
    vault = z > centre[2] + 0.8 * inner[2]  # over the vault: the sagittal sinus alone, in the midline
    assert np.ptp(x[vault]) <= SINUS_MM + 1.0
    back = (y > centre[1] + 0.8 * inner[1]) & (np.abs(x - centre[0]) > SINUS_MM)  # the occiput: the transverse
    assert np.ptp(z[back]) <= SINUS_MM + 1.0
