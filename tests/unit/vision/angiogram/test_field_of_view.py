import numpy as np
import pytest

from dsareg_engine.vision.angiogram.field_of_view import combined_field_of_view, estimate_field_of_view, inner_field
from tests.support.angiogram_images import unsubtracted_angiogram


@pytest.mark.parametrize("field, outside", [("round", 8.0), ("rect", 8.0), ("round", 250.0)])
def test_the_collimated_field_is_found(field, outside):
    pixels, _, truth = unsubtracted_angiogram(field=field, outside_level=outside)
    found = estimate_field_of_view(pixels)
    wrong = found ^ truth
    assert wrong.mean() < 0.01, wrong.mean()


def test_an_uncollimated_image_is_all_field():
    pixels, vessels, _ = unsubtracted_angiogram(field="none")
    assert estimate_field_of_view(pixels).mean() > 0.99


def test_the_files_shutter_narrows_the_field_and_the_margin_erodes_it():
    image_field = np.ones((40, 40), bool)
    shutter = np.zeros((40, 40), bool)
    shutter[5:35, 5:35] = True
    combined = combined_field_of_view(image_field, shutter)
    assert combined.sum() == 900
    assert inner_field(combined, 2).sum() == 26 * 26
    assert inner_field(image_field, 1).sum() == 38 * 38  # the image border counts as outside
