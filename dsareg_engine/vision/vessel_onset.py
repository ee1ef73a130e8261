"""The edge of a projected vessel: a square-root contrast onset, blurred.

A round vessel of radius R is ``2√(2 R s − s²) ≈ 2√(2 R s)`` thick at a distance ``s`` inside its
projected outline; any contrast law is linear in thin layers (``c = f(t)``, ``f(0) = 0``), so near
the outline ``c ∝ √s`` whatever the radius, the peak or the law. The detector (and any smoothing)
blurs that onset by a Gaussian σ; the √ onset has no scale of its own, so the blurred profile is
self-similar, ``c(s) = √σ F(s / σ)``, and two dimensionless ratios of it depend on ``s / σ`` only:

* ``r = c / (2 c')`` (→ ``s`` deep inside, without blur exactly ``s``): the distance to the outline;
* ``q = c c'' / c'²`` (derivatives along the gradient): where on the onset a pixel lies.

From ``q`` a pixel's ``s / σ`` follows, and from ``r`` then σ: the image's own blur, measured on
the edges of wide vessels (:func:`estimate_blur_px`). With σ known, ``r`` gives each edge pixel's
sub-pixel distance to the outline (:func:`outline_distance_px`).
"""

from __future__ import annotations

import cv2
import numpy as np

MIN_EDGE_PIXELS = 200
"""Fewer usable edge pixels than this: the blur is not estimated (``DEFAULT_BLUR_PX``)."""
DEFAULT_BLUR_PX = 0.6
"""Blur σ assumed without an estimate (px; a 0.5-px detector blur and the pixel's own box)."""
BLUR_RANGE_PX = (0.3, 2.0)
"""Estimates are clamped to this range (px)."""


def _onset_tables(step: float = 0.01) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(x, r, q)`` for a √ onset blurred by a unit Gaussian, ``x = s / σ`` from −3 to 5 (r rises, q falls)."""
    u = np.arange(-12.0, 12.0, step)
    kernel = np.exp(-0.5 * np.arange(-6.0, 6.0 + step, step) ** 2)
    profile = np.convolve(np.sqrt(np.maximum(u, 0.0)), kernel / kernel.sum(), mode="same")
    slope = np.gradient(profile, step)
    curvature = np.gradient(slope, step)
    keep = (u > -3.0) & (u < 5.0)
    slope = np.maximum(slope[keep], 1e-12)
    return u[keep], profile[keep] / (2.0 * slope), profile[keep] * curvature[keep] / slope**2


_X, _R, _Q = _onset_tables()


def _derivatives(contrast: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Gradient magnitude and second derivative along the gradient, ``(H, W)`` float64 each."""
    image = contrast.astype(np.float64)
    gx = cv2.Sobel(image, cv2.CV_64F, 1, 0, ksize=3) / 8.0
    gy = cv2.Sobel(image, cv2.CV_64F, 0, 1, ksize=3) / 8.0
    gxx = cv2.Sobel(image, cv2.CV_64F, 2, 0, ksize=3) / 4.0
    gyy = cv2.Sobel(image, cv2.CV_64F, 0, 2, ksize=3) / 4.0
    gxy = cv2.Sobel(image, cv2.CV_64F, 1, 1, ksize=3) / 4.0
    squared = np.maximum(gx * gx + gy * gy, 1e-24)
    return np.sqrt(squared), (gx * gx * gxx + 2.0 * gx * gy * gxy + gy * gy * gyy) / squared


def estimate_blur_px(contrast: np.ndarray, wide_edge: np.ndarray, smooth_px: float, noise_sigma: float) -> float:
    """The image's own blur σ (px, pixel box included) from the edges of wide vessels.

    Args:
        contrast: ``(H, W)`` vessel contrast (bright vessels, background 0).
        wide_edge: ``(H, W)`` bool pixels on the outline of vessels at least ~5 px in radius
            (thin vessels' profiles are not a √ onset at the blur's scale).
        smooth_px: Gaussian σ applied here first (against noise; subtracted again).
        noise_sigma: the contrast's noise σ; pixels below 5 σ of the smoothed noise are skipped.
    """
    light = cv2.GaussianBlur(contrast.astype(np.float32), (0, 0), smooth_px)
    gradient, along = _derivatives(light)
    q = light * along / gradient**2
    floor = 5.0 * noise_sigma / (2.0 * np.sqrt(np.pi) * smooth_px)
    use = wide_edge & (q > _Q.min()) & (q < _Q.max()) & (light > floor)
    if use.sum() < MIN_EDGE_PIXELS:
        return DEFAULT_BLUR_PX
    x = np.interp(q[use], _Q[::-1], _X[::-1])
    total = float(np.median(light[use] / (2.0 * gradient[use]) / np.interp(x, _X, _R)))
    return float(np.clip(np.sqrt(max(total**2 - smooth_px**2, 0.0)), *BLUR_RANGE_PX))


def outline_distance_px(contrast: np.ndarray, blur_px: float) -> np.ndarray:
    """``(H, W)`` float32 signed distance (px, positive inside) of each pixel centre to the vessel outline.

    ``contrast``: vessel contrast whose total blur σ is ``blur_px``. ``r = c / (2|∇c|)`` is mapped
    back through the blurred onset; beyond the table's end it is read as the distance itself
    (deep inside), below its start as 3 σ outside.
    """
    gradient, _ = _derivatives(contrast)
    ratio = np.maximum(contrast, 0.0) / (2.0 * gradient) / blur_px
    inside = np.interp(ratio, _R, _X)
    deep = ratio > _R[-1]
    inside[deep] = ratio[deep]
    return (inside * blur_px).astype(np.float32)
