from dsareg_engine.vision.angiogram import segment_angiogram
from tests.support.angiogram_images import unsubtracted_angiogram


def test_frangi_finds_dark_vessels_and_not_the_field_edge():
    pixels, vessels, field = unsubtracted_angiogram(seed=1)
    result = segment_angiogram(pixels, method="frangi")
    mask = result.mask
    assert result.method == "frangi"
    dice = 2 * (mask & vessels).sum() / (mask.sum() + vessels.sum())
    assert dice > 0.5, dice
    assert mask.mean() < 0.25
