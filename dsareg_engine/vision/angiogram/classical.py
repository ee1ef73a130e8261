"""The classical vessel segmentation of a real X-ray angiogram: the fallback of the network and its comparison.

At the network's working scale (:mod:`.prepare`), inside the field of view (:mod:`.field_of_view`):

1. vessels dark (physics, not a histogram guess: :mod:`.prepare`);
2. background anatomy removed at the vessels' scale: a black top-hat with a disc of ``background_radius_px``
   (wider than any vessel at the working scale; bone edges, the diaphragm and soft tissue are wider or are steps);
3. Frangi vesselness over ``sigmas_px`` (vessels 2–16 px wide), black ridges;
4. hysteresis: pixels above the ``high_quantile`` of the field's response, grown through pixels above the
   ``low_quantile`` (a tree covers a few % of a field: the quantiles say so instead of a fitted level).

Its probability-like output is the response scaled to [0, 1] at the high level (0.5 = the low level), so that
:mod:`.vessel_mask` applies to both paths.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from .field_of_view import inner_field
from .prepare import WorkingScale, working_image


@dataclass(frozen=True)
class ClassicalSettings:
    sigmas_px: tuple[float, ...] = (1.0, 1.5, 2.0, 3.0, 4.0)
    background_radius_px: int = 10
    high_quantile: float = 0.94
    low_quantile: float = 0.88


def classical_probability(pixels: np.ndarray, field: np.ndarray | None = None, *, vessels_dark: bool = True,
                          settings: ClassicalSettings = ClassicalSettings(), scale: WorkingScale = WorkingScale()
                          ) -> tuple[np.ndarray, np.ndarray]:
    """``(vessel probability-like map (H, W) in [0, 1], field of view (H, W) bool)`` (module docstring)."""
    from skimage.filters import apply_hysteresis_threshold, frangi

    work = working_image(pixels, field, vessels_dark=vessels_dark, scale=scale)
    dark, small_field = work.network_input, work.field
    disc = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * settings.background_radius_px + 1,) * 2)
    detail = cv2.morphologyEx(dark, cv2.MORPH_BLACKHAT, disc)
    response = frangi(detail, sigmas=settings.sigmas_px, black_ridges=False)
    inside = inner_field(small_field, 3)
    response[~inside] = 0.0
    values = response[inside] if inside.any() else response.ravel()
    high, low = np.quantile(values, [settings.high_quantile, settings.low_quantile])
    kept = apply_hysteresis_threshold(response, low, high) if high > 0 else np.zeros_like(inside)
    score = np.clip(0.5 * response / max(float(low), 1e-12), 0.0, 1.0).astype(np.float32)
    score[~kept] = np.minimum(score[~kept], 0.49)
    return work.back(score), work.full_field()
