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

from .field_of_view import combined_field_of_view, estimate_field_of_view


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


@dataclass(frozen=True)
class WorkingImage:
    """An image at the working scale. Attributes: network_input (h, w) float32 (:func:`normalized`); field (h, w)
    bool, the field of view there; factor: the averaging factor; shape: the original (H, W); pixels (h, w) float32:
    the averaged image before normalising (a coarser reading starts from it)."""

    network_input: np.ndarray
    field: np.ndarray
    factor: int
    shape: tuple[int, int]
    pixels: np.ndarray

    def back(self, values: np.ndarray) -> np.ndarray:
        """``values (h, w)`` on the original pixels (bilinear), clipped to [0, 1]."""
        return np.clip(grown(values, self.shape), 0.0, 1.0)

    def full_field(self) -> np.ndarray:
        return grown(self.field.astype(np.float32), self.shape) >= 0.5


def working_image(pixels: np.ndarray, field: np.ndarray | None = None, *, vessels_dark: bool = True,
                  scale: WorkingScale = WorkingScale()) -> WorkingImage:
    """``pixels (H, W)`` averaged to the working scale, its field of view found (and narrowed by the file's
    ``field``, if any) and normalised: what both the network and the classical path start from."""
    image = np.asarray(pixels, np.float32)
    factor = averaging_factor(image.shape, scale)
    small = shrunk(image, factor)
    small_file_field = None if field is None else shrunk(field.astype(np.float32), factor) >= 0.5
    small_field = combined_field_of_view(estimate_field_of_view(small), small_file_field)
    return WorkingImage(normalized(small, small_field, vessels_dark=vessels_dark), small_field, factor, image.shape,
                        small)
