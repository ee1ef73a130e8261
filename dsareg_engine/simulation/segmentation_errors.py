"""Simulated segmentation errors, for robustness studies of the registration.

Real DSA vessel masks differ from a mesh's silhouette in predictable ways: borders a pixel
too wide or too narrow (threshold, blur), vessel segments missing (poor filling, overlap,
vessels the 3D model has and the run did not opacify), devices the mesh lacks (catheter,
coils), and speckle from noise or bone subtraction residue. Each function takes a boolean
mask ``(H, W)`` and returns a new one; randomness comes only from the given generator.
"""

from __future__ import annotations

from typing import Callable

import cv2
import numpy as np


def grow_border(mask: np.ndarray, pixels: int = 1) -> np.ndarray:
    """Dilate by ``pixels`` (square structuring element): vessels segmented too wide."""
    return cv2.dilate(mask.astype(np.uint8), np.ones((2 * pixels + 1,) * 2, np.uint8)).astype(bool)


def shrink_border(mask: np.ndarray, pixels: int = 1) -> np.ndarray:
    """Erode by ``pixels``: vessels segmented too narrow; the thinnest ones vanish."""
    return cv2.erode(mask.astype(np.uint8), np.ones((2 * pixels + 1,) * 2, np.uint8)).astype(bool)


def drop_segments(mask: np.ndarray, rng: np.random.Generator, count: int = 3, fraction_of_width: float = 1 / 16) -> np.ndarray:
    """Clear ``count`` squares (side 2·fraction·W px) centred on random vessel pixels."""
    out = mask.copy()
    rows, cols = np.nonzero(mask)
    if rows.size == 0:
        return out
    half = max(1, round(mask.shape[1] * fraction_of_width))
    for index in rng.integers(rows.size, size=count):
        out[max(0, rows[index] - half):rows[index] + half, max(0, cols[index] - half):cols[index] + half] = False
    return out


def add_catheter(mask: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """A curved catheter from the bottom edge into the vessel tree (width ~W/150, ≥ 2 px)."""
    height, width = mask.shape
    rows, cols = np.nonzero(mask)
    tip = (cols.mean(), rows.mean()) if rows.size else (width / 2, height / 2)
    entry = (width * rng.uniform(0.3, 0.7), height - 1.0)
    bend = (0.5 * (entry[0] + tip[0]) + width * rng.uniform(-0.08, 0.08), 0.5 * (entry[1] + tip[1]))
    t = np.linspace(0.0, 1.0, 40)[:, None]
    curve = (1 - t) ** 2 * np.array(entry) + 2 * (1 - t) * t * np.array(bend) + t**2 * np.array(tip)
    image = mask.astype(np.uint8)
    cv2.polylines(image, [np.round(curve).astype(np.int32)], False, 1, thickness=max(2, width // 150))
    return image.astype(bool)


def add_speckle(mask: np.ndarray, rng: np.random.Generator, spots_per_megapixel: float = 1200.0) -> np.ndarray:
    """Scattered false-positive discs of radius 1–2 px over the whole image."""
    height, width = mask.shape
    image = mask.astype(np.uint8)
    for _ in range(round(spots_per_megapixel * height * width / 1e6)):
        cv2.circle(image, (int(rng.integers(width)), int(rng.integers(height))), int(rng.integers(1, 3)), 1, -1)
    return image.astype(bool)


def add_background(mask: np.ndarray, rng: np.random.Generator, blobs: int = 3) -> np.ndarray:
    """Background a segmentation keeps that no vessel model explains: ``blobs`` filled ellipses (semi-axes W/60–W/25,
    overlapping anatomy: bone, air, a subtraction residue) at random places, and the edge of a round field of view
    (a ring 2 px wide, radius 0.46–0.5 W, centred near the image's centre)."""
    height, width = mask.shape
    image = mask.astype(np.uint8)
    for _ in range(blobs):
        centre = (int(rng.integers(width)), int(rng.integers(height)))
        axes = tuple(int(width * rng.uniform(1 / 60, 1 / 25)) for _ in range(2))
        cv2.ellipse(image, centre, axes, float(rng.uniform(0, 180)), 0, 360, 1, -1)
    centre = (int(width / 2 + rng.uniform(-0.02, 0.02) * width), int(height / 2 + rng.uniform(-0.02, 0.02) * height))
    cv2.circle(image, centre, int(width * rng.uniform(0.46, 0.5)), 1, 2)
    return image.astype(bool)


CORRUPTIONS: dict[str, Callable[[np.ndarray, np.random.Generator], np.ndarray]] = {
    "none": lambda mask, rng: mask.copy(),
    "grow_1px": lambda mask, rng: grow_border(mask, 1),
    "shrink_1px": lambda mask, rng: shrink_border(mask, 1),
    "missing_segments": drop_segments,
    "catheter": add_catheter,
    "speckle": add_speckle,
    "background": add_background,
    "all": lambda mask, rng: add_speckle(add_catheter(drop_segments(grow_border(mask, 1), rng), rng), rng),
}
"""Named corruptions for ``python -m benchmarks.engine robustness``; ``all`` chains grow, drop, catheter, speckle."""


def corrupt(mask: np.ndarray, name: str, rng: np.random.Generator) -> np.ndarray:
    """Apply the named corruption; raises ``ValueError`` naming the accepted ones."""
    if name not in CORRUPTIONS:
        raise ValueError(f"unknown corruption {name!r}; accepted: {', '.join(CORRUPTIONS)}")
    return CORRUPTIONS[name](np.asarray(mask, bool), rng)
