"""Where an X-ray angiogram shows the patient: the field of view ``(H, W)`` bool, True inside.

X-ray detectors are collimated: a round image intensifier field, or shutter / collimator blades, leave flat,
featureless regions along the image border (black in most vendors' MONOCHROME2 files, sometimes white). They
carry no vessel, and their edge is the strongest straight or circular ridge in the image, which a vesselness
filter takes for a vessel. The field is found in two ways:

* from the file (:mod:`dsareg_engine.io.xa_shutter`, the DICOM Shutter / Collimator modules) when it says;
* from the image (:func:`estimate_field_of_view`): the flat regions at the darkest or brightest level of the
  flat pixels along the image border (within 4 % of the image's 1–99 % range), connected to the border, where
  that level is an extreme of the image (within 10 % of its 1 or 99 % level). Flat means a
  local standard deviation (7 × 7 px) under a third of the image's own texture (the median local deviation).

Both are combined with :func:`combined_field_of_view` (inside both).
"""

from __future__ import annotations

import cv2
import numpy as np
from scipy import ndimage


def _local_std(image: np.ndarray, size_px: int) -> np.ndarray:
    mean = cv2.blur(image, (size_px, size_px), borderType=cv2.BORDER_REFLECT)
    mean_sq = cv2.blur(image * image, (size_px, size_px), borderType=cv2.BORDER_REFLECT)
    return np.sqrt(np.maximum(mean_sq - mean * mean, 0.0))


def _border_ring(shape: tuple[int, int], width_px: int) -> np.ndarray:
    ring = np.zeros(shape, bool)
    ring[:width_px], ring[-width_px:], ring[:, :width_px], ring[:, -width_px:] = True, True, True, True
    return ring


def estimate_field_of_view(pixels: np.ndarray, *, min_outside_fraction: float = 0.002) -> np.ndarray:
    """The field of view of ``pixels`` ``(H, W)`` as seen in the image: True inside (module docstring).

    All True when no flat border region covers at least ``min_outside_fraction`` of the image (0.2 %: a corner
    cut by a round field).
    """
    image = np.asarray(pixels, np.float32)
    low, high = np.percentile(image, [1.0, 99.0])
    span = float(high - low)
    everything = np.ones(image.shape, bool)
    if span <= 0 or min(image.shape) < 16:
        return everything
    deviation = _local_std(image, 7)
    texture = float(np.median(deviation))
    flat = deviation <= max(0.35 * texture, 1e-3 * span)
    touching_border = _border_ring(image.shape, 1)
    outside = np.zeros(image.shape, bool)
    ring_values = image[_border_ring(image.shape, 2) & flat]
    if ring_values.size < 8:
        return everything
    for level in np.percentile(ring_values, [2.0, 98.0]):
        if min(abs(level - low), abs(level - high)) > 0.1 * span:
            continue  # a flat border region at a mid grey is anatomy, not a shutter
        candidate = flat & (np.abs(image - level) <= 0.04 * span)
        labels, _ = ndimage.label(candidate)
        found = np.unique(labels[touching_border])
        outside |= np.isin(labels, found[found > 0])
    if outside.mean() < min_outside_fraction:
        return everything
    # a pixel is flat when its whole 7 x 7 window is: the flat region stops 3 px short of the field's edge
    outside = cv2.dilate(outside.astype(np.uint8), np.ones((7, 7), np.uint8)).astype(bool)
    return _cleaned(~outside)


def _cleaned(inside: np.ndarray) -> np.ndarray:
    """The largest inside piece, its holes filled, thin bridges cut (3 px opening)."""
    inside = ndimage.binary_opening(inside, structure=np.ones((3, 3), bool), iterations=1)
    labels, count = ndimage.label(inside)
    if count == 0:
        return np.ones(inside.shape, bool)
    sizes = np.bincount(labels.ravel())
    sizes[0] = 0
    return ndimage.binary_fill_holes(labels == int(np.argmax(sizes)))


def combined_field_of_view(from_image: np.ndarray, from_file: np.ndarray | None) -> np.ndarray:
    """Inside both (the file's shutter where the file has one)."""
    if from_file is None or from_file.shape != from_image.shape:
        return from_image
    return from_image & from_file


def inner_field(field: np.ndarray, margin_px: int) -> np.ndarray:
    """``field`` eroded by ``margin_px`` pixels (the image border counts as outside)."""
    if margin_px <= 0:
        return field
    padded = np.pad(field, 1, constant_values=False)
    eroded = cv2.erode(padded.astype(np.uint8), cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * margin_px + 1,) * 2))
    return eroded[1:-1, 1:-1].astype(bool)
