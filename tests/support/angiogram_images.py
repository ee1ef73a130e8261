"""Unsubtracted X-ray angiograms made for tests, with what real ones have and the project's DSA generator lacks:
a collimated field (round or rectangular; black, or white after a MONOCHROME1 inversion) whose edge is a strong
ring, uneven background anatomy (a dark diaphragm-like blob, a bright bone band, smooth texture), noise, and dark
vessels 2–8 px wide on curved paths. Returns the pixels, the true vessels and the true field of view."""

from __future__ import annotations

import cv2
import numpy as np


def _curves(size: int, rng: np.random.Generator, count: int) -> np.ndarray:
    canvas = np.zeros((size, size), np.float32)
    for _ in range(count):
        start = rng.uniform(0.2, 0.8, 2) * size
        angle = rng.uniform(0, 2 * np.pi)
        width = int(rng.integers(3, 8))
        points = [start]
        for _ in range(40):
            angle += rng.normal(0, 0.18)
            points.append(points[-1] + 0.02 * size * np.array([np.cos(angle), np.sin(angle)]))
        cv2.polylines(canvas, [np.round(np.array(points)).astype(np.int32)], False, 1.0, width, cv2.LINE_AA)
    return canvas


def unsubtracted_angiogram(size: int = 256, seed: int = 0, field: str = "round", outside_level: float = 8.0
                           ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(pixels (size, size) float32 in 0–255, vessels bool, field of view bool)``; ``field``: ``"round"``,
    ``"rect"`` or ``"none"``."""
    rng = np.random.default_rng(seed)
    rows, cols = np.mgrid[0:size, 0:size].astype(np.float32) / size
    texture = cv2.resize(rng.normal(0, 1, (6, 6)).astype(np.float32), (size, size), interpolation=cv2.INTER_CUBIC)
    background = 150 + 18 * texture
    background -= 45 * cv2.GaussianBlur(((rows - 0.9) ** 2 / 0.09 + (cols - 0.3) ** 2 / 0.2 < 1).astype(np.float32),
                                        (0, 0), 0.02 * size)
    background += 25 * np.exp(-((cols - 0.75 + 0.3 * rows) / 0.05) ** 2)
    vessels = cv2.GaussianBlur(_curves(size, rng, 5), (0, 0), 0.8)
    pixels = background * (1.0 - 0.4 * np.clip(vessels, 0, 1)) + rng.normal(0, 3.0, (size, size))
    if field == "round":
        inside = (rows - 0.5) ** 2 + (cols - 0.5) ** 2 <= 0.46 ** 2
    elif field == "rect":
        inside = (rows > 0.08) & (rows < 0.9) & (cols > 0.12) & (cols < 0.93)
    else:
        inside = np.ones((size, size), bool)
    pixels = np.where(inside, pixels, outside_level + rng.normal(0, 0.3, (size, size)))
    return np.clip(pixels, 0, 255).astype(np.float32), (vessels >= 0.5) & inside, inside
