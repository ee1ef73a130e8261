"""The mask ↔ contrast shift: recovered against a known sub-pixel shift, vessels present."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from dsareg_engine.vision.xa_motion import estimate_motion, estimate_shift, move_image, shift_image


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


def _blobs(centres: np.ndarray, size: int, sigma_px: float = 4.0) -> np.ndarray:
    """Gaussian blobs drawn analytically at ``centres`` ``(K, 2)`` (column, row)."""
    v, u = np.mgrid[0:size, 0:size].astype(np.float64)
    out = np.zeros((size, size))
    for x, y in centres:
        out += np.exp(-((u - x) ** 2 + (v - y) ** 2) / (2 * sigma_px ** 2))
    return out.astype(np.float32)


@pytest.mark.parametrize("rotation_deg, shift", [(0.5, (0.8, -0.5)), (-1.2, (-1.5, 2.0))])
def test_rotation_and_shift_are_recovered(rotation_deg, shift):
    """Blobs placed by hand at T(p) = R(p − c) + c + s (R counter-clockwise as displayed: a point right of
    the centre goes up), vessels across: the fit recovers θ and s (not only a shift)."""
    size, rng = 384, np.random.default_rng(5)
    centres = rng.uniform(20, size - 20, size=(160, 2))
    c = (size - 1) / 2.0
    theta = np.radians(rotation_deg)
    x, y = centres[:, 0] - c, centres[:, 1] - c
    moved = np.stack([np.cos(theta) * x + np.sin(theta) * y + c + shift[1],
                      -np.sin(theta) * x + np.cos(theta) * y + c + shift[0]], axis=1)
    mask = _blobs(centres, size) + rng.normal(0.0, 0.01, (size, size)).astype(np.float32)
    contrast = _blobs(moved, size) + rng.normal(0.0, 0.01, (size, size)).astype(np.float32)
    contrast[180:186, 10:370] -= 0.8  # a vessel: excluded from the fit
    motion = estimate_motion(mask, contrast)
    assert motion.rotation_deg == pytest.approx(rotation_deg, abs=0.02)
    np.testing.assert_allclose(motion.shift_px, shift, atol=0.05)
    right_of_centre = move_image(_blobs(np.array([[c + 100, c]]), size), (0.0, 0.0), 10.0)
    row, _ = np.unravel_index(np.argmax(right_of_centre), right_of_centre.shape)
    assert row < c - 10  # counter-clockwise as displayed: up
