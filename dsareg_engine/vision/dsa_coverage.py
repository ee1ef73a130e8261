"""Grey-level DSA → per-pixel vessel coverage in [0, 1] with sub-pixel borders (a soft target).

A binary mask puts each border at a contrast level (:mod:`.dsa_border`): a fraction of the local
centreline contrast. Where that level lands depends on the vessel's profile, and so on its size,
on overlapping vessels (a summed peak) and on the contrast law; measured on the paper's mesh it
leaves borders a few tenths of a pixel off, by amounts that differ from vessel to vessel, and the
pose follows (ADD 0.02 mm against 0.003 mm from the true masks).

Here the border is placed where the contrast *starts*: a projected round vessel is
``t(s) ≈ 2√(2 R s)`` thick at a distance ``s`` inside its outline, and any contrast law is linear
in thin layers (``c = f(t)``, ``f(0) = 0``), so near the outline ``c ∝ √s`` and

    ``s = c / (2 |∇c|)``

is the pixel centre's distance to the outline, whatever the vessel's radius, peak or law (deeper
inside the estimate only grows, and the coverage is clipped to 1). The image's blur softens the
onset; it is measured on the edges of wide vessels and undone through the blurred onset's table
(:mod:`.vessel_onset`). The pixel's coverage is the 1-px ramp ``clip(0.5 + s, 0, 1)``, 0 where the
(1-px smoothed) contrast is below 3 noise σ. Which pixels can be vessel at all (detection, catheter
removal, small objects) is the binary mask's decision, dilated by two pixels.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from .dsa_border import dsa_contrast, dsa_vessel_mask
from .vessel_onset import estimate_blur_px, outline_distance_px


@dataclass(frozen=True)
class CoverageSettings:
    """Sub-pixel border from the contrast onset.

    Attributes:
        smooth_px: Gaussian σ (px) applied to the contrast before the onset distance (0: none).
        blur_smooth_px: Gaussian σ (px) applied before estimating the image's blur.
        noise_floor_sigma: pixels whose contrast, smoothed by ``floor_smooth_px``, is below this
            many of its noise σ are 0.
        floor_smooth_px: see ``noise_floor_sigma``.
        reach_px: how far (px) outside the binary mask the border may move.
        wide_radius_px: vessels at least this wide (radius, px) measure the blur.
    """

    smooth_px: float = 0.0
    blur_smooth_px: float = 1.0
    noise_floor_sigma: float = 3.0
    floor_smooth_px: float = 1.0
    reach_px: int = 2
    wide_radius_px: float = 5.0


def dsa_found(bright: np.ndarray, min_object_px: int) -> tuple[np.ndarray, float, np.ndarray]:
    """``(contrast, noise σ, binary mask)`` of a bright-vessel image: the steps the coverage starts from."""
    contrast, sigma = dsa_contrast(bright)
    return contrast, sigma, dsa_vessel_mask(bright, min_object_px, (contrast, sigma))


def _wide_edge(mask: np.ndarray, radius_px: float) -> np.ndarray:
    """``(H, W)`` bool outline pixels (±1 px) of vessels at least ``radius_px`` wide."""
    pixels = mask.astype(np.uint8)
    radius = cv2.dilate(cv2.distanceTransform(pixels, cv2.DIST_L2, cv2.DIST_MASK_PRECISE), np.ones((9, 9), np.uint8))
    edge = cv2.dilate(pixels, np.ones((3, 3), np.uint8)).astype(bool) & ~cv2.erode(pixels, np.ones((3, 3), np.uint8)).astype(bool)
    return edge & (radius >= radius_px)


def dsa_vessel_coverage(bright: np.ndarray, min_object_px: int, settings: CoverageSettings = CoverageSettings(),
                        found: tuple[np.ndarray, float, np.ndarray] | None = None) -> np.ndarray:
    """Vessel coverage ``(H, W)`` float32 in [0, 1] of a bright-vessel float image (see the module docstring).

    ``found``: ``(contrast, noise σ, binary mask)`` of ``bright`` when already computed (:func:`dsa_found`)."""
    contrast, sigma, mask = found if found is not None else dsa_found(bright, min_object_px)
    if not mask.any():
        return mask.astype(np.float32)
    image_blur = estimate_blur_px(contrast, _wide_edge(mask, settings.wide_radius_px), settings.blur_smooth_px, sigma)
    light = cv2.GaussianBlur(contrast, (0, 0), settings.smooth_px) if settings.smooth_px > 0 else contrast
    distance = outline_distance_px(light, float(np.hypot(settings.smooth_px, image_blur)))
    floor_light = cv2.GaussianBlur(contrast, (0, 0), settings.floor_smooth_px)
    floor = settings.noise_floor_sigma * sigma / (2.0 * np.sqrt(np.pi) * settings.floor_smooth_px)  # smoothed white noise
    size = 2 * settings.reach_px + 1
    reach = cv2.dilate(mask.astype(np.uint8), np.ones((size, size), np.uint8)).astype(bool)
    coverage = np.clip(0.5 + distance, 0.0, 1.0)
    coverage[~reach | (floor_light < floor)] = 0.0
    coverage[cv2.erode(mask.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)] = 1.0
    return coverage.astype(np.float32)
