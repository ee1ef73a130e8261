"""A registration's set-up (:mod:`dsareg_engine.registration.preparation`): the stage ladder's coarsest level."""

import numpy as np
import pytest

from dsareg_engine.registration.schedule import build_schedule, pyramid_scales


def _tree_of_extent(side_px: int, extent_px: int) -> dict[str, np.ndarray]:
    """Masks whose vessels span ``extent_px``: only their extent sets the ladder, so they are cut to the tree's box
    (``side_px`` is the image's side, passed to the schedule apart)."""
    mask = np.zeros((extent_px + 10, extent_px // 2 + 30), bool)
    mask[5, 20] = mask[4 + extent_px, 19 + extent_px // 2] = True  # the box's corners: the extent is its longer side
    return {"ap": mask, "lat": mask}


@pytest.mark.parametrize("side_px", [512, 1024])
def test_the_coarsest_level_follows_the_vessels_extent_without_a_cliff(side_px):
    """Two px more or less of the tree move the coarsest level's scale by about 1 % (a cliff was 2×, at 192 px)."""
    from dsareg_engine.registration.options import RegistrationOptions
    from dsareg_engine.registration.preparation import _ladder_schedule

    coarsest = [_ladder_schedule(RegistrationOptions(), side_px, _tree_of_extent(side_px, extent), ("ap", "lat"), 1.0)[0].scale
                for extent in range(100, side_px - 10, 2)]
    steps = np.array(coarsest[:-1]) / np.array(coarsest[1:])
    assert np.all(steps >= 1.0) and steps.max() < 1.03  # monotone: a larger tree, a coarser level; never a jump
    assert coarsest[-1] == pyramid_scales(side_px)[0]  # a tree filling the image: the image's pyramid


def test_a_tree_filling_the_image_keeps_the_image_pyramid():
    from dsareg_engine.registration.options import RegistrationOptions
    from dsareg_engine.registration.preparation import _ladder_schedule

    for extent in (400, 630, 750):  # the paper's mesh spans 631-750 px at 800 px (Table 1)
        stages = _ladder_schedule(RegistrationOptions(), 800, _tree_of_extent(800, extent), ("ap", "lat"), 1.0)
        assert [stage.scale for stage in stages] == [stage.scale for stage in build_schedule("simultaneous", 800, 300)]
