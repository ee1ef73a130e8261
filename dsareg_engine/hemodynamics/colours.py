"""The arrival-time colour scale shared by the coloured model and the parametric maps.

Times from ``low_s`` (earliest) to ``high_s`` (latest) run through OpenCV's Turbo map: dark blue (early) →
cyan → green → yellow → red → dark red (late); a point without a value is mid grey ``NULL_RGB``. The scale's
ends are the 2nd and 98th percentiles of the values shown, so one outlier does not compress the rest.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

NULL_RGB = (128, 128, 128)
PERCENTILES = (2.0, 98.0)


@dataclass(frozen=True)
class TimeScale:
    """Arrival times ``low_s`` .. ``high_s`` → colours."""

    low_s: float
    high_s: float

    @classmethod
    def of(cls, values_s: np.ndarray) -> TimeScale:
        finite = np.asarray(values_s, float)[np.isfinite(values_s)]
        if len(finite) == 0:
            return cls(0.0, 1.0)
        low, high = np.percentile(finite, PERCENTILES)
        return cls(float(low), float(max(high, low + 1e-3)))

    def levels(self, values_s: np.ndarray) -> np.ndarray:
        """``uint8`` 0..255 along the scale (NaN → 0)."""
        fraction = (np.nan_to_num(np.asarray(values_s, float), nan=self.low_s) - self.low_s) / (self.high_s - self.low_s)
        return np.clip(np.round(255 * fraction), 0, 255).astype(np.uint8)

    def rgb(self, values_s: np.ndarray) -> np.ndarray:
        """``(..., 3)`` uint8 RGB; NaN → ``NULL_RGB``."""
        values = np.asarray(values_s, float)
        bgr = cv2.applyColorMap(self.levels(values).reshape(-1, 1), cv2.COLORMAP_TURBO).reshape(*values.shape, 3)
        rgb = bgr[..., ::-1].copy()
        rgb[~np.isfinite(values)] = NULL_RGB
        return rgb

    def describe(self) -> str:
        return (f"arrival time colour scale: Turbo colour map from {self.low_s:.2f} s (dark blue, earliest) to "
                f"{self.high_s:.2f} s (dark red, latest), seconds from the first AP frame; grey = not measured")
