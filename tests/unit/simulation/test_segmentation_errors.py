"""Simulated segmentation errors: each does what it says, reproducibly."""

import numpy as np
import pytest

from dsareg_engine.simulation.segmentation_errors import CORRUPTIONS, add_background, add_catheter, add_speckle, corrupt, drop_segments, grow_border, shrink_border


@pytest.fixture()
def vessel():
    mask = np.zeros((120, 160), bool)
    mask[20:100, 78:84] = True  # a 6-px vertical vessel
    mask[58:62, 40:120] = True  # a 4-px horizontal branch
    return mask


def test_grow_and_shrink_move_the_border_by_one_pixel(vessel):
    grown, shrunk = grow_border(vessel), shrink_border(vessel)
    assert grown[20:100, 77:85].all() and not grown[20:56, 86].any()
    assert shrunk[21:99, 79:83].all() and not shrunk[:56, 78].any()
    assert shrunk.sum() < vessel.sum() < grown.sum()
    assert not shrink_border(vessel, 3)[58:62, 40:70].any()  # a 4-px branch vanishes under a 3-px erosion


def test_random_corruptions_are_reproducible_and_local(vessel):
    for function in (drop_segments, add_catheter, add_speckle):
        first = function(vessel, np.random.default_rng(4))
        assert np.array_equal(first, function(vessel, np.random.default_rng(4)))
        assert not np.array_equal(first, vessel)
    dropped = drop_segments(vessel, np.random.default_rng(0))
    assert not (dropped & ~vessel).any()  # only removes
    catheter = add_catheter(vessel, np.random.default_rng(0))
    assert (catheter & vessel).sum() == vessel.sum() and catheter[-1].any()  # adds, enters at the bottom edge


def test_corrupt_names_the_accepted_corruptions(vessel):
    assert set(CORRUPTIONS) >= {"none", "grow_1px", "shrink_1px", "missing_segments", "catheter", "speckle", "all"}
    assert np.array_equal(corrupt(vessel, "none", np.random.default_rng(0)), vessel)
    with pytest.raises(ValueError, match="accepted: none, grow_1px"):
        corrupt(vessel, "blur", np.random.default_rng(0))


def test_background_adds_blobs_and_a_field_of_view_ring_away_from_the_vessels(vessel):
    added = add_background(vessel, np.random.default_rng(0))
    assert (added & vessel).sum() == vessel.sum() and added.sum() > 1.5 * vessel.sum()  # only adds, and a lot
    assert added[:, :5].any() and added[:, -5:].any() and added[:5].any() and added[-5:].any()  # the ring near the edges
    assert np.array_equal(added, corrupt(vessel, "background", np.random.default_rng(0)))
