"""An X-ray angiogram made ready for the vessel network: polarity, working scale, intensity normalisation.

* **Polarity from physics.** Iodine attenuates X-rays, so in an X-ray image as the reader delivers it (MONOCHROME2
  after :mod:`dsareg_engine.io.image_io` has inverted MONOCHROME1 and applied the modality LUT) vessels are darker
  than their surroundings, native or subtracted alike. The network sees vessels dark; nothing is guessed from
  the histogram (a black shutter and a few bright pixels move a median anywhere). ``vessels_dark=False`` is only
  for images known to be inverted (a mask, a display-inverted export).
* **Working scale.** The network was trained on ~300 px images in which coronary arteries are 3–15 px wide, with
  scale augmentation 0.6–1.6×. Larger images are area-averaged by the integer factor that brings the longest side
  to at most ``max_side_px`` (1024² → 512², 2048² → 512²); the probability is resized back.
* **Normalisation.** Inside the field of view the 0.5–99.5 % grey levels map to [0, 1], then to zero mean and unit
  deviation; outside the field of view the input is 0 (the mean), so the field's edge is no contrast at all.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np


@dataclass(frozen=True)
class WorkingScale:
    """Attributes:
        max_side_px: the longest side the network works at (larger images are area-averaged by an integer factor).
    """

    max_side_px: int = 512


def averaging_factor(shape: tuple[int, int], scale: WorkingScale = WorkingScale()) -> int:
    """The integer factor that brings the longest side of ``shape`` to at most ``scale.max_side_px``."""
    return max(1, int(np.ceil(max(shape) / scale.max_side_px)))


def shrunk(image: np.ndarray, factor: int, *, interpolation: int = cv2.INTER_AREA) -> np.ndarray:
    """``image (H, W)`` resized by ``1 / factor`` (area averaging)."""
    if factor <= 1:
        return image
    height, width = image.shape
    size = (max(1, round(width / factor)), max(1, round(height / factor)))
    return cv2.resize(image.astype(np.float32), size, interpolation=interpolation)


def grown(image: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """``image`` bilinearly resized to ``shape (H, W)`` (half-pixel centres)."""
    if image.shape == tuple(shape):
        return image
    return cv2.resize(image.astype(np.float32), (shape[1], shape[0]), interpolation=cv2.INTER_LINEAR)


def normalized(pixels: np.ndarray, field: np.ndarray, *, vessels_dark: bool = True) -> np.ndarray:
    """The network's input ``(H, W)`` float32: vessels dark, normalised inside ``field``, 0 outside (module doc)."""
    image = np.asarray(pixels, np.float32)
    inside = image[field] if field.any() else image.ravel()
    low, high = np.percentile(inside, [0.5, 99.5])
    scaled = np.clip((image - low) / max(float(high - low), 1e-6), 0.0, 1.0)
    if not vessels_dark:
        scaled = 1.0 - scaled
    values = scaled[field] if field.any() else scaled.ravel()
    mean, deviation = float(values.mean()), float(values.std())
    result = (scaled - mean) / max(deviation, 1e-3)
    result[~field] = 0.0
    return result.astype(np.float32)
