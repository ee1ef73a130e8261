"""Border correction: shifted targets, the area-matching update, and its effect on a registration."""

import numpy as np
import pytest

from dsareg_engine.errors import DsaregInputError
from dsareg_engine.registration import RegistrationOptions
from dsareg_engine.registration.solver import register
from dsareg_engine.registration.border import MAX_BORDER_SHIFT_PX, update_border_shift
from dsareg_engine.registration.targets import binary_mask, shifted_mask, signed_border_distance
from dsareg_engine.simulation.segmentation_errors import grow_border


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


def test_signed_distance_in_the_mask_box_equals_the_whole_image_one():
    import cv2

    from dsareg_engine.registration.targets import SIGNED_DISTANCE_REACH_PX, signed_border_distance

    mask = np.zeros((300, 400), bool)
    mask[100:140, 150:160] = True
    mask[120:125, 150:260] = True
    pixels = mask.astype(np.uint8)
    whole = np.where(mask, 0.5 - cv2.distanceTransform(pixels, cv2.DIST_L2, cv2.DIST_MASK_PRECISE),
                     cv2.distanceTransform(1 - pixels, cv2.DIST_L2, cv2.DIST_MASK_PRECISE) - 0.5)
    signed = signed_border_distance(mask)
    near = whole <= SIGNED_DISTANCE_REACH_PX - 0.5
    assert near.sum() > mask.sum() and np.allclose(signed[near], whole[near], atol=1e-5)
    assert np.all(signed[~near] >= SIGNED_DISTANCE_REACH_PX - 0.5)


def test_border_update_is_the_same_for_a_small_tree_in_a_large_image():
    silhouette = _bar()
    mask = grow_border(silhouette)
    mask[5:8, 100:150] = True  # a catheter-like extra away from the vessel
    large_mask, large_silhouette = (np.pad(image, ((300, 200), (250, 350))) for image in (mask, silhouette))
    for shift in (0.0, -0.7, 1.3):
        assert update_border_shift(large_mask, large_silhouette, shift) == pytest.approx(
            update_border_shift(mask, silhouette, shift), abs=1e-6)  # float32 sums in another order


def test_outline_length_is_skimage_perimeter():
    import cv2
    from skimage.measure import perimeter

    from dsareg_engine.registration.border import outline_length_px

    rng = np.random.default_rng(0)
    blobs = cv2.GaussianBlur(rng.random((120, 160)), (0, 0), 4) > 0.5
    blobs[0, :40] = True  # touching the image border
    cross = cv2.getStructuringElement(cv2.MORPH_CROSS, (3, 3))
    for image in (blobs, _bar(), np.zeros((10, 10), bool)):
        boundary = image & (cv2.erode(image.astype(np.uint8), cross, borderValue=0) == 0)
        assert outline_length_px(boundary) == pytest.approx(perimeter(image), abs=1e-9)
