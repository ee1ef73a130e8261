"""Arrival time, time to peak and peak opacity of time–density curves (definitions: docs/concepts/hemodynamics.md).

For a curve ``c(t)`` (background-corrected opacity, :mod:`.sampling`) sampled at the frame times ``t_k``:

* **baseline**: the median of ``c`` over the run's frames before contrast arrives anywhere (the frames before
  the mean curve of all points first reaches ``RUN_ARRIVAL_FRACTION`` of its maximum); 0 when there are none;
* **peak** (``peak_s``, ``peak_opacity``): the highest sample above the baseline, refined between frames by the
  least-squares parabola through the samples within ``PEAK_WINDOW_S`` of it (at least its two neighbours; its
  vertex, kept within them);
* **arrival** (``arrival_s``): when the curve rises through half its own peak: the last upward crossing of
  ``baseline + ½ peak`` before the peak frame, interpolated linearly between the two frames around it; not
  measurable (NaN) when the first frame is already above it;
* **filled**: the peak stands ``SIGNIFICANCE_SIGMAS`` times above the noise of the curve (the spread a footprint
  of that many pixels shows on background pixels between frames, :func:`mean_noise`) and reaches
  ``MIN_FILL_FRACTION`` of what a vessel of that size shows in this run (the median opacity per mm of mean path
  through the vessel over its footprint, over the significant points: a thin vessel whose footprint reaches past
  its walls is expected to show less). A curve that is not filled never saw contrast: every value is NaN.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from .gamma_fit import gamma_variate

RUN_ARRIVAL_FRACTION = 0.1
SIGNIFICANCE_SIGMAS = 5.0
MIN_FILL_FRACTION = 0.4
NOISE_RADII_PX = (0.5, 1.0, 2.0, 4.0, 8.0, 16.0)
NOISE_SAMPLE_STEP = 3
PEAK_WINDOW_S = 0.35


@dataclass(frozen=True)
class CurveParameters:
    """Per point ``(N,)``: ``arrival_s``, ``peak_s``, ``peak_opacity`` (NaN where not measurable), ``filled``
    (bool), ``noise`` (the curve's noise, opacity units); ``mtt_s``, ``area``: the gamma-variate fit
    (:mod:`.gamma_fit`) when asked for."""

    arrival_s: np.ndarray
    peak_s: np.ndarray
    peak_opacity: np.ndarray
    filled: np.ndarray
    noise: np.ndarray
    mtt_s: np.ndarray | None = None
    area: np.ndarray | None = None


def _noise_levels(stack: np.ndarray, background: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(pixels (L,), noise (L,))``: the noise of the mean over each disc of ``NOISE_RADII_PX`` (its pixel count),
    measured on the run itself: the robust spread of disc-averaged frame-to-frame differences over ``background``
    ``(H, W)`` bool (every ``NOISE_SAMPLE_STEP``-th pixel each way), ÷ √2."""
    pairs = np.linspace(0, len(stack) - 2, min(3, len(stack) - 1)).round().astype(int)
    sample = np.zeros(background.shape, bool)
    sample[::NOISE_SAMPLE_STEP, ::NOISE_SAMPLE_STEP] = True
    sample &= background
    pixels, levels = [], []
    for radius in NOISE_RADII_PX:
        size = 2 * int(np.ceil(radius)) + 1
        yy, xx = np.mgrid[:size, :size] - size // 2
        kernel = (np.hypot(xx, yy) <= radius).astype(np.float32)
        pixels.append(kernel.sum())
        kernel /= kernel.sum()
        spreads = []
        for k in pairs:
            diff = cv2.filter2D((stack[k + 1] - stack[k]).astype(np.float32), -1, kernel)[sample]
            spreads.append(1.4826 * np.median(np.abs(diff - np.median(diff))) / np.sqrt(2.0))
        levels.append(float(np.median(spreads)) if spreads else 0.0)
    return np.array(pixels, float), np.array(levels, float)


def footprint_noise(stack: np.ndarray, background: np.ndarray, radii_px: np.ndarray) -> np.ndarray:
    """``(N,)``: the noise of a footprint mean over a disc of radius ``radii_px`` ``(N,)`` (:func:`_noise_levels`,
    interpolated in log–log between the measured radii)."""
    logs = np.log(np.maximum(_noise_levels(stack, background)[1], 1e-12))
    return np.exp(np.interp(np.log(np.maximum(radii_px, 1e-6)), np.log(NOISE_RADII_PX), logs))


def mean_noise(stack: np.ndarray, background: np.ndarray, pixels: np.ndarray) -> np.ndarray:
    """``(N,)``: the noise of a mean over ``pixels`` ``(N,)`` neighbouring pixels (a footprint or a ring as sampled,
    whatever its shape; :func:`_noise_levels`, interpolated in log–log between the discs' pixel counts; one pixel
    at least). What the curve of a footprint of a few pixels shows, which its nominal radius would understate."""
    counts, levels = _noise_levels(stack, background)
    logs = np.log(np.maximum(levels, 1e-12))
    return np.exp(np.interp(np.log(np.maximum(pixels, 1.0)), np.log(counts), logs))


def baseline_frames(curves: np.ndarray) -> int:
    """How many frames come before contrast arrives anywhere (from the mean curve ``(T,)`` of all points)."""
    mean = np.nanmean(curves, axis=0) if len(curves) else np.zeros(1)
    mean = mean - mean[0]
    if mean.max() <= 0:
        return 0
    return int(np.argmax(mean >= RUN_ARRIVAL_FRACTION * mean.max()))


def _parabola_peak(times: np.ndarray, curves: np.ndarray, k: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Sub-frame peak (time, value): the vertex of the least-squares parabola through the frames within
    ``PEAK_WINDOW_S`` of frame ``k`` (at least its two neighbours), kept within them; the frame itself at the ends
    or when the parabola does not open downward."""
    half = max(1, int(round(PEAK_WINDOW_S / max(float(np.median(np.diff(times))), 1e-9)))) if len(times) > 1 else 1
    rows = np.arange(len(k))[:, None]
    window = np.clip(k[:, None] + np.arange(-half, half + 1)[None], 0, len(times) - 1)
    x = times[window] - times[k][:, None]  # (N, M) s from the frame of the highest sample
    y = curves[rows, window]
    powers = np.stack([x ** 2, x, np.ones_like(x)], axis=2)  # (N, M, 3)
    normal = powers.transpose(0, 2, 1) @ powers
    inner = (k > 0) & (k < len(times) - 1)
    normal[~inner] = np.eye(3)
    a, b, c = np.linalg.solve(normal, (powers.transpose(0, 2, 1) @ y[..., None]))[..., 0].T
    with np.errstate(divide="ignore", invalid="ignore"):
        vertex = np.clip(-b / (2 * a), x.min(axis=1), x.max(axis=1))
    ok = inner & (a < 0) & np.isfinite(vertex)
    shift = np.where(ok, vertex, 0.0)
    value = np.where(ok, a * shift ** 2 + b * shift + c, curves[rows[:, 0], k])
    return times[k] + shift, value


def _half_rise(times: np.ndarray, curves: np.ndarray, k: np.ndarray, half: np.ndarray) -> np.ndarray:
    """The last upward crossing of ``half`` before frame ``k``, interpolated (NaN when frame 0 is above it)."""
    frames = np.arange(curves.shape[1])
    below = (curves < half[:, None]) & (frames[None] < k[:, None])
    last_below = np.where(below.any(axis=1), curves.shape[1] - 1 - np.argmax(below[:, ::-1], axis=1), -1)
    rows = np.arange(len(k))
    j = np.clip(last_below, 0, curves.shape[1] - 2)
    c0, c1 = curves[rows, j], curves[rows, j + 1]
    with np.errstate(divide="ignore", invalid="ignore"):
        fraction = np.clip((half - c0) / (c1 - c0), 0.0, 1.0)
    arrival = times[j] + fraction * (times[j + 1] - times[j])
    return np.where(last_below >= 0, arrival, np.nan)


def lift(curves: np.ndarray, measurable: np.ndarray) -> np.ndarray:
    """``curves`` ``(N, T)`` less each one's baseline (the median before the run's contrast arrives, measured on
    the ``measurable`` ones' mean curve)."""
    start = baseline_frames(curves[measurable]) if measurable.any() else 0
    base = np.median(curves[:, :start], axis=1) if start > 0 else np.zeros(len(curves))
    return curves - base[:, None]


def curve_parameters(curves: np.ndarray, times_s: np.ndarray, noise: np.ndarray, chord_mm: np.ndarray,
                     measurable: np.ndarray, typical_per_mm: float | None = None, gamma_fit: bool = False
                     ) -> CurveParameters:
    """Parameters of ``curves`` ``(N, T)`` at ``times_s`` ``(T,)``; ``noise`` ``(N,)`` the curves' noise,
    ``chord_mm`` ``(N,)`` the mean path through each vessel over its footprint (:func:`.sampling.mean_chord_mm`: what a
    filled vessel there shows, relative), ``measurable`` ``(N,)`` bool (the rest: NaN, not filled);
    ``typical_per_mm``: what a filled vessel shows per mm when known (else the median over these curves);
    ``gamma_fit``: also fit the gamma variate (``mtt_s``, ``area``)."""
    times = np.asarray(times_s, float)
    count = len(curves)
    lifted = lift(curves, measurable)
    k = np.argmax(lifted, axis=1)
    peak_s, peak = _parabola_peak(times, lifted, k)
    significant = measurable & (peak > SIGNIFICANCE_SIGMAS * np.maximum(noise, 1e-12))
    per_mm = peak / np.maximum(chord_mm, 1e-6)
    typical = typical_per_mm if typical_per_mm is not None else \
        float(np.median(per_mm[significant])) if significant.any() else 0.0
    filled = significant & (per_mm >= MIN_FILL_FRACTION * typical)
    arrival = _half_rise(times, lifted, k, 0.5 * peak)
    nan = np.full(count, np.nan)
    arrival, peak_s, peak = np.where(filled, arrival, nan), np.where(filled, peak_s, nan), np.where(filled, peak, nan)
    mtt, area = gamma_variate(times, lifted, arrival, peak_s, peak) if gamma_fit else (None, None)
    return CurveParameters(arrival, peak_s, peak, filled, noise, mtt, area)
