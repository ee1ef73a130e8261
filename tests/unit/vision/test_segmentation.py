import numpy as np
import pytest

from dsareg_engine.errors import DsaregInputError
from dsareg_engine.geometry.rig import ViewGeometry
from dsareg_engine.vision.segmentation import resample_mask, segment_vessels, vessels_are_dark


def dice(a, b):
    return 2 * np.logical_and(a, b).sum() / (a.sum() + b.sum())


@pytest.mark.parametrize("method", ["auto", "otsu", "vesselness"])
def test_dsa_dark_vessels(build, method):
    image, truth = build.dsa()
    assert vessels_are_dark(image)
    mask = segment_vessels(image, method)
    assert mask.dtype == bool and mask.shape == image.shape
    assert dice(mask, truth) > 0.75


@pytest.mark.parametrize("method", ["otsu", "vesselness"])
def test_polarity_bright_vessels(build, method):
    image, truth = build.dsa()
    bright = 255 - image
    assert not vessels_are_dark(bright)
    assert dice(segment_vessels(bright, method), segment_vessels(image, method)) > 0.98


def test_vesselness_keeps_the_thin_vessel(build):
    image, truth = build.dsa(height=128, width=160, seed=3)
    rows, cols = np.mgrid[0:128, 0:160]
    thin = np.abs(cols - (160 * 0.6 + 0.1 * rows)) < 1.2
    thin &= ~(np.abs(rows - (0.3 * cols + 20)) < 6)  # away from the crossing
    mask = segment_vessels(image, "vesselness")
    assert mask[thin].mean() > 0.8


def test_masks_used_as_they_are():
    mask = np.zeros((40, 50), np.uint8)
    mask[10:30, 20:24] = 255
    np.testing.assert_array_equal(segment_vessels(mask, "auto"), mask > 0)
    np.testing.assert_array_equal(segment_vessels(255 - mask, "auto"), mask > 0)  # black vessels on white
    np.testing.assert_array_equal(segment_vessels(mask > 0, "otsu"), mask > 0)  # a bool array is a mask
    soft = mask.astype(np.float32) / 255 * 0.9 + 0.05  # anti-aliased export
    np.testing.assert_array_equal(segment_vessels(soft, "mask"), mask > 0)


def test_errors():
    with pytest.raises(DsaregInputError, match="constant") as info:
        segment_vessels(np.full((20, 20), 7.0), "otsu", field_name="lat")
    assert info.value.field == "lat"
    with pytest.raises(DsaregInputError, match="unknown segmentation"):
        segment_vessels(np.eye(20), "magic")
    with pytest.raises(DsaregInputError, match="no vessel"):
        segment_vessels(np.zeros((20, 20), bool))
    with pytest.raises(DsaregInputError, match="2D"):
        segment_vessels(np.zeros((2, 20, 20)))


def test_resample_mask_rescales_geometry():
    view = ViewGeometry(
        (200, 100),
        (0.3, 0.3),
        1000.0,
        (99.5, 49.5),
        np.diag([1.0, 1.0, 1.0, 1.0]) + np.array([[0, 0, 0, 0], [0, 0, 0, 0], [0, 0, 0, 700.0], [0, 0, 0, 0]]),
    )
    mask = np.zeros((100, 200), bool)
    mask[40:60, 10:190] = True
    small, small_view = resample_mask(mask, view, 50)
    assert small.shape == (25, 50) and small_view.image_size == (50, 25)
    point = np.array([[12.0, -5.0, 30.0]])
    u, v = view.project(point)[0]
    np.testing.assert_allclose(small_view.project(point)[0], [0.25 * (u + 0.5) - 0.5, 0.25 * (v + 0.5) - 0.5])
    assert small[12, 25] and not small[2, 25]
    same, same_view = resample_mask(mask, view, 0)
    assert same is mask and same_view is view
