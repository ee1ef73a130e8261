import numpy as np

from dsareg_engine.vision.angiogram.augment import _shuttered, augmented_sample
from tests.support.angiogram_images import unsubtracted_angiogram


def test_samples_are_crops_normalised_with_labels_inside_the_field():
    pixels, vessels, _ = unsubtracted_angiogram(size=96, seed=1)
    rng = np.random.default_rng(0)
    for _ in range(6):
        image, label = augmented_sample(pixels, vessels, rng, 48)
        assert image.shape == label.shape == (48, 48) and image.dtype == np.float32
        assert set(np.unique(label)) <= {0.0, 1.0}


def test_a_shutter_hides_the_vessels_outside_it():
    pixels, vessels, _ = unsubtracted_angiogram(size=96, seed=2, field="none")
    unit = pixels / 255.0
    rng = np.random.default_rng(3)
    shuttered, label = _shuttered(unit, vessels, rng)
    outside = shuttered != unit
    assert outside.any() and not label[outside].any()
