"""The flat-field correction auto's choice reads the network on (issue 40: a vignetted image intensifier)."""

import numpy as np

from dsareg_engine.vision.flat_field import MIN_BACKGROUND_PX, fitted_surface, flat_fielded


def _vignetted(size: int = 200, seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(image, vessels, gain): dark straight vessels on a flat level, a vignette 1 − 0.175 r² and a ±15 % gradient
    added (log-domain image), noise σ 1."""
    rng = np.random.default_rng(seed)
    rows, cols = np.mgrid[0:size, 0:size].astype(np.float64)
    r2 = ((rows - size / 2) ** 2 + (cols - size / 2) ** 2) / (size / 2) ** 2
    gain = 100.0 * (-0.175 * r2 + 0.3 * (cols / size - 0.5))
    vessels = (np.abs(rows - 0.4 * cols - 40) < 4) | (np.abs(cols - 120) < 2)
    image = 800.0 + gain - 60.0 * vessels + rng.normal(0, 1.0, (size, size))
    return image.astype(np.float32), vessels, gain


def test_the_smooth_gain_is_removed_and_the_vessels_kept():
    image, vessels, gain = _vignetted()
    surface = fitted_surface(image, np.ones(image.shape, bool))  # vessels included: the robust rounds drop them
    residual = surface - gain - 800.0
    assert np.abs(residual - residual.mean()).max() < 1.5
    corrected = flat_fielded(image, ~vessels)
    background = corrected[~vessels]
    assert background.std() < 1.2 and image[~vessels].std() > 10  # flat after, 1 σ of noise; ~ 20 σ of gain before
    assert abs(float(np.median(corrected[vessels]) - np.median(background)) + 60.0) < 2.0  # contrast unchanged


def test_outside_the_field_and_without_background_nothing_changes():
    image, vessels, _ = _vignetted()
    field = np.zeros(image.shape, bool)
    field[20:180, 20:180] = True
    corrected = flat_fielded(image, field & ~vessels, field)
    assert np.array_equal(corrected[~field], image[~field])
    few = np.zeros(image.shape, bool)
    few.flat[: MIN_BACKGROUND_PX - 1] = True
    assert flat_fielded(image, few) is None
