"""Parametric colour-coded DSA: each pixel of a run coloured by its own contrast arrival time, with a colour bar.

Per pixel, the frames (lightly smoothed, Gaussian σ ``SMOOTH_PX``) give a time–density curve; its arrival
(half-peak rise) and peak are found as for the model's points (:mod:`.parameters`), with the noise of one
smoothed pixel in its own region: a run's noise is not the same everywhere (fewer photons through the skull), so
``NOISE_BLOCK_PX`` blocks each measure theirs on the frames before contrast arrives, never below the run's
(:func:`regional_noise`); with one noise for the whole run, the noisier regions showed coloured speckles. Pixels
whose peak is not significant stay black; the others take the arrival's colour
(:mod:`.colours`, the same scale as the model), brighter where the peak opacity is higher. A colour bar on the
right carries the time scale in seconds.
Brightness: ``0.45 + 0.55 √(peak / the 99th-percentile peak)``.
"""

from __future__ import annotations

import cv2
import numpy as np

from .colours import TimeScale
from .parameters import SIGNIFICANCE_SIGMAS, baseline_frames, curve_parameters, footprint_noise

SMOOTH_PX = 1.0
BAR_WIDTH_PX = 90
NOISE_BLOCK_PX = 16
MAD_TO_SIGMA = 1.4826  # a normal distribution's σ per median absolute deviation


def regional_noise(smooth: np.ndarray, floor: float) -> np.ndarray:
    """``(H, W)``: one smoothed pixel's noise around each pixel, at least ``floor``: per ``NOISE_BLOCK_PX`` block,
    the robust spread of the frame-to-frame changes before contrast arrives (vessels do not change then),
    interpolated between block centres; ``floor`` everywhere when fewer than two such frames exist."""
    frames, height, width = smooth.shape
    before = baseline_frames(smooth.mean(axis=(1, 2))[None])  # the mean curve of all pixels, in image order
    if before < 2:
        return np.full((height, width), floor, np.float32)
    changes = np.abs(np.diff(smooth[:before], axis=0))
    rows, cols = -(-height // NOISE_BLOCK_PX), -(-width // NOISE_BLOCK_PX)
    padded = np.pad(changes, ((0, 0), (0, rows * NOISE_BLOCK_PX - height), (0, cols * NOISE_BLOCK_PX - width)),
                    mode="edge")
    blocks = padded.reshape(len(changes), rows, NOISE_BLOCK_PX, cols, NOISE_BLOCK_PX).transpose(1, 3, 0, 2, 4)
    spread = np.median(blocks.reshape(rows, cols, -1), axis=2) * MAD_TO_SIGMA / np.sqrt(2.0)  # a difference of two
    noise = cv2.resize(spread.astype(np.float32), (width, height), interpolation=cv2.INTER_LINEAR)
    return np.maximum(noise, floor)


def pixel_arrival(opacity: np.ndarray, times_s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(arrival_s (H, W), peak opacity (H, W))`` per pixel; NaN where not significant. Only pixels whose
    highest value stands ``SIGNIFICANCE_SIGMAS`` above the noise are measured (the rest cannot be filled)."""
    smooth = np.stack([cv2.GaussianBlur(frame, (0, 0), SMOOTH_PX) for frame in opacity.astype(np.float32)])
    height, width = smooth.shape[1:]
    noise = regional_noise(smooth, float(footprint_noise(smooth, np.ones((height, width), bool), np.array([1.0]))[0]))
    candidates = np.flatnonzero(((smooth.max(axis=0) - smooth[0]) > SIGNIFICANCE_SIGMAS * noise).ravel())
    arrival = np.full(height * width, np.nan)
    peak = np.full(height * width, np.nan)
    if len(candidates):
        curves = smooth.reshape(len(smooth), -1)[:, candidates].T
        count = len(candidates)
        found = curve_parameters(curves, times_s, noise.ravel()[candidates], np.ones(count), np.ones(count, bool))
        arrival[candidates], peak[candidates] = found.arrival_s, found.peak_opacity
    return arrival.reshape(height, width), peak.reshape(height, width)


def colour_bar(scale: TimeScale, height: int) -> np.ndarray:
    """``(height, BAR_WIDTH_PX, 3)`` BGR: the scale from early (bottom) to late (top), ticks in seconds."""
    panel = np.full((height, BAR_WIDTH_PX, 3), 32, np.uint8)
    top, bottom = 30, height - 20
    values = np.linspace(scale.high_s, scale.low_s, max(bottom - top, 2))
    panel[top:bottom, 12:32] = scale.rgb(values)[:, None, ::-1]
    for value in np.linspace(scale.low_s, scale.high_s, 5):
        row = int(round(top + (scale.high_s - value) / (scale.high_s - scale.low_s) * (bottom - top - 1)))
        cv2.line(panel, (32, row), (38, row), (230, 230, 230), 1)
        cv2.putText(panel, f"{value:.1f}", (41, row + 4), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (230, 230, 230), 1, cv2.LINE_AA)
    cv2.putText(panel, "arrival", (6, 12), cv2.FONT_HERSHEY_SIMPLEX, 0.38, (230, 230, 230), 1, cv2.LINE_AA)
    cv2.putText(panel, "time (s)", (6, 24), cv2.FONT_HERSHEY_SIMPLEX, 0.38, (230, 230, 230), 1, cv2.LINE_AA)
    return panel


def parametric_image(arrival_s: np.ndarray, peak: np.ndarray, scale: TimeScale, title: str) -> np.ndarray:
    """``(H, W + bar, 3)`` BGR uint8: the colour-coded run, its colour bar and a title."""
    colour = scale.rgb(arrival_s)[..., ::-1].astype(np.float32)
    finite = np.isfinite(peak)
    top = float(np.percentile(peak[finite], 99)) if finite.any() else 1.0
    brightness = np.where(finite, 0.45 + 0.55 * np.sqrt(np.clip(np.nan_to_num(peak) / max(top, 1e-9), 0.0, 1.0)), 0.0)
    image = (colour * brightness[..., None]).astype(np.uint8)
    image[~finite] = 0
    if image.shape[0] < 160:
        factor = int(np.ceil(160 / image.shape[0]))
        image = cv2.resize(image, None, fx=factor, fy=factor, interpolation=cv2.INTER_NEAREST)
    cv2.putText(image, title, (6, 16), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (255, 255, 255), 1, cv2.LINE_AA)
    return np.concatenate([image, colour_bar(scale, image.shape[0])], axis=1)
