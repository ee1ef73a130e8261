"""Patient motion between the mask and a contrast frame: a sub-pixel translation found on the background.

Both images are in the log domain (:mod:`.xa_run`). The mask is moved by ``s = (down, right)`` px,
``M_s(x) = M(x − s)``, and ``s`` minimizes ``Σ w(x) (C(x) − M_s(x))²`` over the background:
Gauss–Newton on the two shift parameters (``M_{s+δ} ≈ M_s − ∇M_s · δ``), started from a phase
correlation of the band-passed images. The weights ``w`` leave out the vessels and anything
else that does not move rigidly: pixels darkened by contrast (the residual below −3 σ, widened by
a few pixels) and every residual beyond 3 σ (σ: the residual's robust spread), re-chosen at each
step, and a margin at the image border.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np


@dataclass(frozen=True)
class MotionSettings:
    """Attributes:
        iterations: Gauss–Newton steps.
        smooth_px: Gaussian σ applied to both images before estimating (noise).
        vessel_margin_px: how far the excluded contrast region is widened.
        max_shift_px: larger estimates are refused (the run is left uncorrected, with a warning).
    """

    iterations: int = 12
    smooth_px: float = 1.0
    vessel_margin_px: int = 3
    max_shift_px: float = 20.0


def shift_image(image: np.ndarray, shift_px: tuple[float, float]) -> np.ndarray:
    """``image`` moved by ``(down, right)`` px (bicubic, border replicated)."""
    down, right = shift_px
    if down == 0 and right == 0:
        return image
    matrix = np.array([[1.0, 0.0, right], [0.0, 1.0, down]], np.float64)
    return cv2.warpAffine(image.astype(np.float32), matrix, image.shape[::-1], flags=cv2.INTER_CUBIC,
                          borderMode=cv2.BORDER_REPLICATE)


def _robust_sigma(values: np.ndarray) -> float:
    return float(1.4826 * np.median(np.abs(values - np.median(values)))) + 1e-12


def _initial_shift(mask: np.ndarray, contrast: np.ndarray) -> tuple[float, float]:
    """Phase correlation of the band-passed images (vessels and all; a start only)."""
    def band(image):
        return (cv2.GaussianBlur(image, (0, 0), 1.0) - cv2.GaussianBlur(image, (0, 0), 6.0)).astype(np.float32)
    window = cv2.createHanningWindow(mask.shape[::-1], cv2.CV_32F)
    (right, down), _ = cv2.phaseCorrelate(band(mask), band(contrast), window)
    return float(down), float(right)


def estimate_shift(mask: np.ndarray, contrast: np.ndarray, settings: MotionSettings = MotionSettings()
                   ) -> tuple[tuple[float, float], float]:
    """``((down, right) px, residual σ)``: the move of ``mask`` that best matches ``contrast`` on the background.

    Args:
        mask, contrast: ``(H, W)`` log-domain images of the same size.
    """
    mask = cv2.GaussianBlur(mask.astype(np.float32), (0, 0), settings.smooth_px)
    contrast = cv2.GaussianBlur(contrast.astype(np.float32), (0, 0), settings.smooth_px)
    shift = np.array(_initial_shift(mask, contrast))
    if not np.all(np.isfinite(shift)) or np.abs(shift).max() > settings.max_shift_px:
        shift = np.zeros(2)
    height, width = mask.shape
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * settings.vessel_margin_px + 1,) * 2)
    sigma = 0.0
    for _ in range(settings.iterations):
        moved = shift_image(mask, tuple(shift))
        residual = contrast - moved
        sigma = _robust_sigma(residual)
        vessels = cv2.dilate((residual < -3.0 * sigma).astype(np.uint8), kernel).astype(bool)
        weight = (~vessels) & (np.abs(residual) < 3.0 * sigma)
        border = int(np.ceil(np.abs(shift).max())) + 3
        weight[:border], weight[-border:], weight[:, :border], weight[:, -border:] = False, False, False, False
        gy = cv2.Sobel(moved, cv2.CV_32F, 0, 1, ksize=3) / 8.0
        gx = cv2.Sobel(moved, cv2.CV_32F, 1, 0, ksize=3) / 8.0
        g = np.stack([gy[weight], gx[weight]], axis=1).astype(np.float64)
        r = residual[weight].astype(np.float64)
        normal = g.T @ g
        if len(r) < 16 or np.linalg.cond(normal) > 1e8:
            break
        step = np.linalg.solve(normal, g.T @ r)  # C − M_{s+δ} ≈ r + ∇M_s·δ, least squares: δ = −(gᵀg)⁻¹ gᵀ r
        shift = shift - step
        if np.abs(step).max() < 1e-3:
            break
    if np.abs(shift).max() > settings.max_shift_px or not np.all(np.isfinite(shift)):
        return (0.0, 0.0), sigma
    return (float(shift[0]), float(shift[1])), sigma
