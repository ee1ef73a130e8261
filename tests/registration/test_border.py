"""Border correction: shifted targets, the area-matching update, and its effect on a registration."""

import numpy as np
import pytest

from dsareg_engine.registration import RegistrationOptions, register
from dsareg_engine.registration.border import MAX_BORDER_SHIFT_PX, update_border_shift
from dsareg_engine.errors import DsaregInputError
from dsareg_engine.registration.targets import binary_mask, shifted_mask, signed_border_distance
from dsareg_engine.segmentation_errors import grow_border


def _bar(width: int = 6) -> np.ndarray:
    """A horizontal vessel, 220 px long."""
    mask = np.zeros((40, 260), bool)
    mask[17:17 + width, 20:240] = True
    return mask


def test_shifted_mask_moves_a_straight_border_by_the_shift():
    bar = _bar()
    assert np.array_equal(shifted_mask(bar, 0.0), bar.astype(np.float32))
    column = 130  # away from the bar's ends
    assert shifted_mask(bar, 1.0)[:, column].sum() == pytest.approx(8.0)
    assert shifted_mask(bar, -1.0)[:, column].sum() == pytest.approx(4.0)
    assert shifted_mask(bar, 0.25)[:, column].sum() == pytest.approx(6.5)  # sub-pixel: a quarter pixel on each side
    assert np.array_equal(shifted_mask(bar, 1.0)[:, column] > 0.5, grow_border(bar)[:, column])


def _soft_bar(edge: float = 0.3) -> np.ndarray:
    """The bar with one more row each side covered by ``edge``: a sub-pixel border 0.5 + edge px out."""
    coverage = _bar().astype(np.float32)
    coverage[16, 20:240] = coverage[23, 20:240] = edge
    return coverage


def test_a_coverage_target_keeps_its_sub_pixel_border():
    coverage = _soft_bar()
    column = 130
    assert np.array_equal(shifted_mask(coverage, 0.0), coverage)  # fitted as it is
    signed = signed_border_distance(coverage)
    assert signed[16, column] == pytest.approx(0.2) and signed[17, column] == pytest.approx(-0.5)
    assert shifted_mask(coverage, 0.25)[:, column].sum() == pytest.approx(6.6 + 0.5)  # each partial pixel + 0.25
    assert np.array_equal(binary_mask(coverage), _bar()) and np.array_equal(binary_mask(_bar()), _bar())


def test_the_border_update_reads_a_coverage_target_to_sub_pixel():
    silhouette = _bar()
    # the target lies 0.3 px wider each side: the update moves its border 0.3 px inward
    assert update_border_shift(_soft_bar(0.3), silhouette, 0.0) == pytest.approx(-0.3, abs=0.03)


def test_register_rejects_coverage_outside_zero_one(phantom, synthetic_case):
    rig, masks = synthetic_case(phantom, 64, 0.0, 0.0)
    bad = {name: mask.astype(np.float32) * 1.5 for name, mask in masks.items()}
    with pytest.raises(DsaregInputError, match=r"\[0, 1\]"):
        register(phantom, bad, rig, RegistrationOptions(starts=1))


def test_update_recovers_a_one_pixel_wider_segmentation():
    silhouette = _bar()
    mask = grow_border(silhouette)  # the segmentation is 1 px wider all round
    shift = 0.0
    for _ in range(3):
        shift = update_border_shift(mask, silhouette, shift)
    assert shift == pytest.approx(-1.0, abs=0.15)
    assert update_border_shift(silhouette, silhouette, 0.0) == pytest.approx(0.0, abs=1e-9)
    assert update_border_shift(mask, np.zeros_like(mask), 0.3) == 0.3  # nothing rendered: unchanged
    assert update_border_shift(np.ones_like(mask), silhouette, 0.0) == -MAX_BORDER_SHIFT_PX  # clamped


def test_update_ignores_structures_away_from_the_model():
    silhouette = _bar()
    mask = silhouette.copy()
    mask[:, 20:60] = False  # a vessel segment the image did not show
    mask[2:8, 100:115] = True  # a blob (device, residue) away from the model
    assert update_border_shift(mask, silhouette, 0.0) == pytest.approx(0.0, abs=0.1)
    assert update_border_shift(grow_border(mask), silhouette, 0.0) == pytest.approx(-1.0, abs=0.15)


def test_border_correction_removes_the_bias_of_a_too_wide_segmentation(phantom, synthetic_case):
    rig, masks = synthetic_case(phantom, 400, 5.0, 5.0)
    wide = {view: grow_border(mask) for view, mask in masks.items()}
    errors = {}
    for correction in (False, True):
        options = RegistrationOptions(border_correction=correction, ground_truth_mesh_to_world=np.eye(4).tolist())
        result = register(phantom, wide, rig, options)
        errors[correction] = result.metrics["ground_truth"]["add_mm"]
    assert errors[False] > 0.1  # the fit reads the wider vessels partly as magnification
    assert errors[True] < 0.05, errors
    shifts = result.metrics["border_shift_px"]
    assert set(shifts) == {"ap", "lat"} and all(-1.4 < value < -0.6 for value in shifts.values()), shifts
