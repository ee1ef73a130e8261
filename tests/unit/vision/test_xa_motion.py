"""The mask ↔ contrast shift: recovered against a known sub-pixel shift, vessels present."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from dsareg_engine.vision.xa_motion import estimate_shift, shift_image


def _anatomy(rng, size=128):
    texture = cv2.GaussianBlur(rng.normal(size=(size, size)).astype(np.float32), (0, 0), 3.0) * 8.0
    v, u = np.mgrid[0:size, 0:size]
    return texture + 1.0 * (((u - 60) / 48.0) ** 2 + ((v - 70) / 40.0) ** 2 < 1)


@pytest.mark.parametrize("truth", [(0.6, -0.35), (-1.7, 2.25), (0.0, 0.0)])
def test_known_shift_is_recovered(truth):
    rng = np.random.default_rng(3)
    anatomy = _anatomy(rng)
    contrast = shift_image(anatomy, truth).copy()
    contrast[60:65, 10:118] -= 0.6  # a vessel: excluded from the fit
    contrast[20:100, 90:94] -= 0.4
    contrast += rng.normal(0.0, 0.01, contrast.shape).astype(np.float32)
    mask = anatomy + rng.normal(0.0, 0.01, anatomy.shape).astype(np.float32)
    found, sigma = estimate_shift(mask, contrast)
    np.testing.assert_allclose(found, truth, atol=0.03)
    assert sigma < 0.03


def test_shift_image_moves_content_down_and_right():
    image = np.zeros((9, 9), np.float32)
    image[4, 4] = 1.0
    moved = shift_image(image, (2.0, 1.0))
    assert np.unravel_index(np.argmax(moved), moved.shape) == (6, 5)
