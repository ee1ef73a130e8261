"""Training augmentation for the vessel network: what varies between X-ray angiograms of other sites.

Each sample is one labelled image changed the ways real acquisitions differ from the training set (the DCA1-style
coronary images: 300² px, round field of view, unsubtracted): scale (0.6–1.6×: detector pitch, magnification,
working size), orientation (flips, quarter turns), exposure (gamma, contrast, noise, blur), and the collimation:
a round or rectangular black or white shutter (outside: no vessel) and semi-transparent collimator blades along a
side (vessels still seen through them). The field of view is then found and the image normalised exactly as at
inference (:mod:`.field_of_view`, :mod:`.prepare`), so the network learns on what it will be given.
"""

from __future__ import annotations

import cv2
import numpy as np

from .field_of_view import estimate_field_of_view
from .prepare import normalized


def _scaled(image: np.ndarray, label: np.ndarray, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    factor = float(np.exp(rng.uniform(np.log(0.6), np.log(1.6))))
    size = (max(32, round(image.shape[1] * factor)), max(32, round(image.shape[0] * factor)))
    interpolation = cv2.INTER_AREA if factor < 1 else cv2.INTER_LINEAR
    image = cv2.resize(image, size, interpolation=interpolation)
    label = cv2.resize(label.astype(np.float32), size, interpolation=cv2.INTER_LINEAR) >= 0.5
    return image, label


def _oriented(image: np.ndarray, label: np.ndarray, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    turns = int(rng.integers(4))
    image, label = np.rot90(image, turns), np.rot90(label, turns)
    if rng.random() < 0.5:
        image, label = image[:, ::-1], label[:, ::-1]
    return np.ascontiguousarray(image), np.ascontiguousarray(label)


def _exposed(image: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """``image`` in [0, 1] with another gamma, contrast, blur and noise."""
    image = np.clip(image, 0.0, 1.0) ** float(np.exp(rng.uniform(np.log(0.6), np.log(1.6))))
    image = 0.5 + (image - 0.5) * rng.uniform(0.6, 1.3) + rng.uniform(-0.1, 0.1)
    if rng.random() < 0.3:
        image = cv2.GaussianBlur(image, (0, 0), rng.uniform(0.5, 1.2))
    if rng.random() < 0.5:
        image = image + rng.normal(0.0, rng.uniform(0.005, 0.04), image.shape).astype(np.float32)
    return image.astype(np.float32)


def _shuttered(image: np.ndarray, label: np.ndarray, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """A round or rectangular shutter at a black or white level: nothing is seen (nor labelled) outside."""
    height, width = image.shape
    rows, cols = np.mgrid[0:height, 0:width]
    if rng.random() < 0.5:
        radius = rng.uniform(0.45, 0.75) * max(height, width)
        centre = (rng.uniform(0.35, 0.65) * height, rng.uniform(0.35, 0.65) * width)
        inside = (rows - centre[0]) ** 2 + (cols - centre[1]) ** 2 <= radius ** 2
    else:
        top, left = rng.uniform(0, 0.2, 2) * (height, width)
        bottom, right = (1 - rng.uniform(0, 0.2, 2)) * (height, width)
        inside = (rows >= top) & (rows < bottom) & (cols >= left) & (cols < right)
    level = rng.uniform(-0.05, 0.08) if rng.random() < 0.8 else rng.uniform(0.95, 1.05)
    image = np.where(inside, image, level).astype(np.float32)
    return image, label & inside


def _bladed(image: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """A semi-transparent collimator blade along one side, its edge straight and slightly tilted."""
    height, width = image.shape
    rows, cols = np.mgrid[0:height, 0:width].astype(np.float32)
    depth = rng.uniform(0.05, 0.25)
    tilt = rng.uniform(-0.1, 0.1)
    side = int(rng.integers(4))
    distance = [rows / height, 1 - rows / height, cols / width, 1 - cols / width][side]
    along = [cols / width, cols / width, rows / height, rows / height][side]
    covered = distance < depth + tilt * (along - 0.5)
    attenuation = rng.uniform(0.35, 0.75)
    return np.where(covered, image * attenuation, image).astype(np.float32)


def augmented_sample(image: np.ndarray, label: np.ndarray, rng: np.random.Generator, crop_px: int
                     ) -> tuple[np.ndarray, np.ndarray]:
    """One training pair ``(input (crop, crop) float32, label (crop, crop) float32)`` from ``image`` (grey levels,
    vessels dark) and ``label`` (bool), changed as the module docstring says and normalised as at inference."""
    low, high = np.percentile(image, [0.5, 99.5])
    unit = np.clip((image.astype(np.float32) - low) / max(float(high - low), 1e-6), 0, 1)
    unit, label = _scaled(unit, label, rng)
    unit, label = _oriented(unit, label, rng)
    unit = _exposed(unit, rng)
    if rng.random() < 0.25:
        unit = _bladed(unit, rng)
    if rng.random() < 0.4:
        unit, label = _shuttered(unit, label, rng)
    field = estimate_field_of_view(unit)
    network_input = normalized(unit, field)
    label = label & field
    return _cropped(network_input, label.astype(np.float32), rng, crop_px)


def _cropped(image: np.ndarray, label: np.ndarray, rng: np.random.Generator, crop_px: int
             ) -> tuple[np.ndarray, np.ndarray]:
    pad_h, pad_w = max(0, crop_px - image.shape[0]), max(0, crop_px - image.shape[1])
    if pad_h or pad_w:
        image = np.pad(image, ((0, pad_h), (0, pad_w)))
        label = np.pad(label, ((0, pad_h), (0, pad_w)))
    top = int(rng.integers(image.shape[0] - crop_px + 1))
    left = int(rng.integers(image.shape[1] - crop_px + 1))
    return image[top:top + crop_px, left:left + crop_px], label[top:top + crop_px, left:left + crop_px]
