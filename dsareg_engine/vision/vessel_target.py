"""What registration fits per view: a vessel mask (bool) or a vessel coverage map (float in [0, 1]).

Numpy only, so that loading a case does not load the registration (torch).
"""

from __future__ import annotations

import numpy as np


def is_coverage(target: np.ndarray) -> bool:
    """True for a soft target (float vessel coverage in [0, 1]); false for a binary mask (bool)."""
    return np.issubdtype(np.asarray(target).dtype, np.floating)


def binary_mask(target: np.ndarray) -> np.ndarray:
    """``(H, W)`` bool: a mask unchanged, a coverage map where it covers at least half a pixel."""
    return target >= 0.5 if is_coverage(target) else np.asarray(target, bool)
