import numpy as np

from dsareg_engine.vision.angiogram.prepare import averaging_factor, grown, normalized, shrunk


def test_working_scale_brings_the_longest_side_to_512_or_less():
    assert averaging_factor((300, 300)) == 1
    assert averaging_factor((512, 512)) == 1
    assert averaging_factor((1024, 1024)) == 2
    assert averaging_factor((2048, 1500)) == 4
    image = np.arange(1024 * 1024, dtype=np.float32).reshape(1024, 1024)
    assert shrunk(image, 2).shape == (512, 512)
    assert grown(shrunk(image, 2), (1024, 1024)).shape == (1024, 1024)


def test_normalized_inside_the_field_and_zero_outside():
    rng = np.random.default_rng(0)
    pixels = rng.uniform(50, 200, (64, 64)).astype(np.float32)
    field = np.zeros((64, 64), bool)
    field[8:56, 8:56] = True
    pixels[~field] = 0.0
    result = normalized(pixels, field)
    assert abs(float(result[field].mean())) < 1e-4 and abs(float(result[field].std()) - 1) < 1e-3
    assert not result[~field].any()
    inverted = normalized(pixels, field, vessels_dark=False)
    assert np.corrcoef(result[field], inverted[field])[0, 1] < -0.99
