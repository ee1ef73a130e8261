"""Patient motion between the mask and a contrast frame: a rigid in-plane move found on the background.

Both images are in the log domain (:mod:`dsareg_engine.io.xa_run`). The mask is moved by ``T``:
turned by ``θ`` about the image centre ``c`` (counter-clockwise as displayed: a point right of the
centre moves up), then shifted by ``s = (down, right)`` px. In column/row coordinates ``z = (x, y)``
(rows down), ``T(z) = R_θ (z − c) + c + s`` with ``R_θ = [[cos θ, sin θ], [−sin θ, cos θ]]`` (OpenCV's
``getRotationMatrix2D`` convention), and the moved mask is ``M_T(z) = M(T⁻¹(z))``.

``T`` minimizes ``Σ w(z) (C(z) − M_T(z))²`` over the background: Gauss–Newton on ``(s, θ)``. A small
extra move ``δ(z) = δs + δθ · J (z − c)``, ``J = [[0, 1], [−1, 0]]`` (the derivative of ``R_θ`` at 0),
changes the moved mask by ``−∇M_T · δ``, so ``δ`` solves the weighted least squares of
``r + ∇M_T · δ = 0`` with ``r = C − M_T``; composing it after ``T`` adds ``δθ`` to ``θ`` and
``δs + δθ J s`` to ``s``. Coarse to fine: the estimate starts on a copy of both images area-averaged
to at most ``coarse_side_px`` (from a phase correlation of the band-passed images, shift only), and is
refined at each finer level up to at most ``fine_side_px``. The weights ``w`` leave out the vessels
and anything else that does not move rigidly: pixels darkened by contrast (the residual below −3 σ,
widened by a few pixels) and every residual beyond 3 σ (σ: the residual's robust spread), re-chosen
at each step, and a margin at the image border. Without rotation (``rotation=False``) only ``s`` is fitted.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np


@dataclass(frozen=True)
class MotionSettings:
    """Attributes:
        iterations: Gauss–Newton steps per level.
        smooth_px: Gaussian σ applied to both images before estimating (noise), per level.
        vessel_margin_px: how far the excluded contrast region is widened.
        max_shift_px, max_rotation_deg: larger estimates are refused (left uncorrected, with a warning).
        rotation: fit the rotation too (else a translation only).
        coarse_side_px, fine_side_px: the coarsest and finest levels' largest side.
        tolerance_px: a level ends when a step moves less than this (px, the rotation at the image edge).
    """

    iterations: int = 12
    smooth_px: float = 1.0
    vessel_margin_px: int = 3
    max_shift_px: float = 20.0
    max_rotation_deg: float = 3.0
    rotation: bool = True
    coarse_side_px: int = 256
    fine_side_px: int = 1024
    tolerance_px: float = 2e-3


@dataclass(frozen=True)
class Motion:
    """A rigid move of the mask onto the contrast frame: ``shift_px`` ``(down, right)`` and ``rotation_deg``
    (counter-clockwise as displayed, about the image centre); ``residual_sigma``: the background misfit."""

    shift_px: tuple[float, float] = (0.0, 0.0)
    rotation_deg: float = 0.0
    residual_sigma: float = 0.0

    @property
    def none(self) -> bool:
        return self.shift_px == (0.0, 0.0) and self.rotation_deg == 0.0


def rigid_matrix(shape: tuple[int, int], shift_px: tuple[float, float], rotation_deg: float) -> np.ndarray:
    """The ``2 × 3`` matrix of ``T`` (column/row coordinates) for an image of ``shape`` ``(H, W)``."""
    theta = np.radians(rotation_deg)
    cos, sin = np.cos(theta), np.sin(theta)
    rotation = np.array([[cos, sin], [-sin, cos]])
    centre = np.array([(shape[1] - 1) / 2.0, (shape[0] - 1) / 2.0])
    offset = centre - rotation @ centre + np.array([shift_px[1], shift_px[0]])
    return np.hstack([rotation, offset[:, None]])


def move_image(image: np.ndarray, shift_px: tuple[float, float], rotation_deg: float = 0.0) -> np.ndarray:
    """``image`` turned by ``rotation_deg`` about its centre, then moved by ``(down, right)`` px (bicubic)."""
    if rotation_deg == 0.0 and shift_px[0] == 0 and shift_px[1] == 0:
        return image
    return cv2.warpAffine(image.astype(np.float32), rigid_matrix(image.shape, shift_px, rotation_deg),
                          image.shape[::-1], flags=cv2.INTER_CUBIC, borderMode=cv2.BORDER_REPLICATE)


def shift_image(image: np.ndarray, shift_px: tuple[float, float]) -> np.ndarray:
    """``image`` moved by ``(down, right)`` px (bicubic, border replicated)."""
    return move_image(image, shift_px, 0.0)


def _robust_sigma(values: np.ndarray) -> float:
    """1.4826 × the median absolute deviation, of at most ~16 k samples (every k-th value: the weights only need σ to a few %)."""
    values = values.ravel()[::max(1, values.size // 16384)]
    return float(1.4826 * np.median(np.abs(values - np.median(values)))) + 1e-12


def _initial_shift(mask: np.ndarray, contrast: np.ndarray) -> tuple[float, float]:
    """Phase correlation of the band-passed images (vessels and all; a start only)."""
    def band(image):
        return (cv2.GaussianBlur(image, (0, 0), 1.0) - cv2.GaussianBlur(image, (0, 0), 6.0)).astype(np.float32)
    window = cv2.createHanningWindow(mask.shape[::-1], cv2.CV_32F)
    (right, down), _ = cv2.phaseCorrelate(band(mask), band(contrast), window)
    return float(down), float(right)


def _weights(residual: np.ndarray, sigma: float, shift: np.ndarray, settings: MotionSettings) -> np.ndarray:
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * settings.vessel_margin_px + 1,) * 2)
    vessels = cv2.dilate((residual < -3.0 * sigma).astype(np.uint8), kernel).astype(bool)
    weight = (~vessels) & (np.abs(residual) < 3.0 * sigma)
    border = int(np.ceil(np.abs(shift).max())) + 3 + int(0.02 * max(residual.shape))
    weight[:border], weight[-border:], weight[:, :border], weight[:, -border:] = False, False, False, False
    return weight


def _refine(mask: np.ndarray, contrast: np.ndarray, shift: np.ndarray, theta: float, settings: MotionSettings
            ) -> tuple[np.ndarray, float, float]:
    """Gauss–Newton at one level: ``(shift (down, right) px, θ rad, residual σ)``."""
    height, width = mask.shape
    half = max(height, width) / 2.0  # the rotation's column scaled to px at the image's edge
    rows, cols = np.mgrid[0:height, 0:width].astype(np.float32)
    rows -= (height - 1) / 2.0
    cols -= (width - 1) / 2.0
    sigma = 0.0
    for _ in range(settings.iterations):
        moved = move_image(mask, (float(shift[0]), float(shift[1])), float(np.degrees(theta)))
        residual = contrast - moved
        sigma = _robust_sigma(residual)
        weight = _weights(residual, sigma, shift, settings)
        gy = cv2.Sobel(moved, cv2.CV_32F, 0, 1, ksize=3)[weight] / 8.0
        gx = cv2.Sobel(moved, cv2.CV_32F, 1, 0, ksize=3)[weight] / 8.0
        columns = [gy, gx] + ([(gx * rows[weight] - gy * cols[weight]) / half] if settings.rotation else [])
        g = np.stack(columns, axis=1).astype(np.float64)
        r = residual[weight].astype(np.float64)
        normal = g.T @ g
        if len(r) < 16 or np.linalg.cond(normal) > 1e8:
            break
        step = -np.linalg.solve(normal, g.T @ r)
        d_theta = step[2] / half if settings.rotation else 0.0
        shift = shift + step[:2] + d_theta * np.array([-shift[1], shift[0]])  # δθ J s in (down, right)
        theta += d_theta
        if np.abs(step).max() < settings.tolerance_px:
            break
    return shift, theta, sigma


def _levels(shape: tuple[int, int], settings: MotionSettings) -> list[int]:
    """Downsampling factors, coarsest first, the finest at most ``fine_side_px``."""
    side = max(shape)
    finest = max(1, int(np.ceil(side / settings.fine_side_px)))
    factors = [finest]
    while side / factors[-1] > settings.coarse_side_px * 1.5:
        factors.append(factors[-1] * 2)
    return factors[::-1]


def _reduced(image: np.ndarray, factor: int, smooth_px: float) -> np.ndarray:
    image = image.astype(np.float32)
    if factor > 1:
        image = cv2.resize(image, (image.shape[1] // factor, image.shape[0] // factor), interpolation=cv2.INTER_AREA)
    return cv2.GaussianBlur(image, (0, 0), smooth_px)


def estimate_motion(mask: np.ndarray, contrast: np.ndarray, settings: MotionSettings = MotionSettings(),
                    start: Motion | None = None) -> Motion:
    """The rigid move of ``mask`` that best matches ``contrast`` on the background (``(H, W)`` log-domain
    images of the same size); no move when the estimate is out of bounds or not finite. ``start`` (e.g.
    another frame's move): refined at the coarsest level only (the other frames of a combined image)."""
    factors = _levels(mask.shape, settings)
    shift, theta, sigma = None, 0.0, 0.0
    if start is not None and not start.none:
        factors, previous = factors[:1], factors[0]
        shift, theta = np.array(start.shift_px) / factors[0], np.radians(start.rotation_deg)
    for factor in factors:
        small_mask, small_contrast = _reduced(mask, factor, settings.smooth_px), _reduced(contrast, factor, settings.smooth_px)
        if shift is None:
            shift = np.array(_initial_shift(small_mask, small_contrast))
            if not np.all(np.isfinite(shift)) or np.abs(shift).max() * factor > settings.max_shift_px:
                shift = np.zeros(2)
        else:
            shift = shift * (previous / factor)
        # the level's centre differs from the full image's by the cropped remainder: negligible at these sizes
        shift, theta, sigma = _refine(small_mask, small_contrast, shift, theta, settings)
        previous = factor
    shift = shift * factors[-1]
    if (not np.all(np.isfinite(shift)) or not np.isfinite(theta) or np.abs(shift).max() > settings.max_shift_px
            or abs(np.degrees(theta)) > settings.max_rotation_deg):
        return Motion(residual_sigma=sigma)
    return Motion((float(shift[0]), float(shift[1])), float(np.degrees(theta)), sigma)


def estimate_shift(mask: np.ndarray, contrast: np.ndarray, settings: MotionSettings = MotionSettings(rotation=False)
                   ) -> tuple[tuple[float, float], float]:
    """``((down, right) px, residual σ)``: the translation only (:func:`estimate_motion` without rotation)."""
    motion = estimate_motion(mask, contrast, settings)
    return motion.shift_px, motion.residual_sigma
