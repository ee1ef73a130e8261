"""The cisterns' sleeve of CSF: where it lies, checked against the distance to a straight vessel computed directly."""

import numpy as np

from dsareg_engine.simulation.cisterns import Cisterns, cistern_mask


def test_the_sleeve_lies_around_the_vessel_between_the_skull_base_and_its_reach():
    spacing = np.array([0.5, 0.5, 1.0])
    occupancy = np.zeros((20, 30, 40), np.float32)
    occupancy[10, 15, :] = 1.0  # a vessel along z, one voxel wide
    occupancy[11, 15, :] = 0.4  # partial volume below one half: not the vessel
    z_mm = (100.0 + np.arange(40) * spacing[2]).reshape(1, 1, -1)
    mask = cistern_mask(occupancy, spacing, z_mm, floor_z_mm=110.0, cisterns=Cisterns(sleeve_mm=2.0, reach_mm=15.0))
    i, j, _ = np.meshgrid(*[np.arange(n) for n in occupancy.shape], indexing="ij")
    radial_mm = np.hypot((i - 10) * spacing[0], (j - 15) * spacing[1])  # the distance to the vessel's axis
    levels = (z_mm >= 110.0) & (z_mm < 125.0)
    expected = (radial_mm <= 2.0) & (radial_mm > 0) & levels
    assert np.array_equal(mask, expected)
    assert mask[10, 11, 20] and not mask[10, 10, 20]  # 2.0 mm from the axis in, 2.5 mm out
    assert not mask[:, :, :10].any() and not mask[:, :, 25:].any()  # below the skull base's top, beyond the reach
