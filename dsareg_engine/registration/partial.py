"""Partial visibility: a model holding more vessels than the images show.

Two measures per view, from the model's hard silhouette ``S`` and the vessel mask ``M`` (both
``(H, W)`` bool, full resolution), each counting a pixel as matched within ``MATCH_TOLERANCE_PX``
of the other:

* ``unmatched``: the fraction of the silhouette farther than that from any vessel — model
  branches the run did not fill (or a wrong pose);
* ``uncovered``: the fraction of the vessels farther than that from the silhouette — vessels
  the model lacks (or a wrong pose).

A pose that explains every vessel while part of the model lies on background, in every view,
reads as partial visibility (:func:`looks_partial`). Then the loss stops forcing the unfilled
branches into the image: background pixels farther than ``NEAR_VESSEL_PX`` (at each pyramid
level) from the vessels weigh ``FAR_BACKGROUND_WEIGHT`` (:func:`trimmed_weight`); near the vessels,
where the pose is decided, every pixel keeps its weight, so the fit stays exact where model and
images agree.
"""

from __future__ import annotations

import cv2
import numpy as np

MATCH_TOLERANCE_PX = 2.0
NEAR_VESSEL_PX = 2
FAR_BACKGROUND_WEIGHT = 0.05
PARTIAL_UNMATCHED = 0.1
"""Partial visibility: at least this fraction of the model's silhouette unmatched in every view..."""
PARTIAL_UNCOVERED = 0.05
"""... while at most this fraction of the vessels is uncovered in every view."""


def _near(mask: np.ndarray, tolerance_px: float) -> np.ndarray:
    return cv2.distanceTransform((~mask).astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE) <= tolerance_px


def match_fractions(silhouette: np.ndarray, mask: np.ndarray, tolerance_px: float = MATCH_TOLERANCE_PX) -> dict:
    """``{"unmatched": …, "uncovered": …}`` of one view (see the module); 1.0 where the silhouette / mask is empty."""
    unmatched = float((silhouette & ~_near(mask, tolerance_px)).sum() / silhouette.sum()) if silhouette.any() else 1.0
    uncovered = float((mask & ~_near(silhouette, tolerance_px)).sum() / mask.sum()) if mask.any() else 1.0
    return {"unmatched": unmatched, "uncovered": uncovered}


def unmatched_pixels(silhouette: np.ndarray, mask: np.ndarray, tolerance_px: float = MATCH_TOLERANCE_PX) -> np.ndarray:
    """``(H, W)`` bool: silhouette pixels farther than ``tolerance_px`` from any vessel of ``mask``."""
    return silhouette & ~_near(mask, tolerance_px)


def looks_partial(fractions: dict[str, dict]) -> bool:
    """True when every view's ``match_fractions`` say: all vessels explained, part of the model unmatched."""
    return all(f["unmatched"] >= PARTIAL_UNMATCHED and f["uncovered"] <= PARTIAL_UNCOVERED for f in fractions.values())


def trimmed_weight(level_target: np.ndarray) -> np.ndarray:
    """``(H, W)`` float32 pixel weights of one level: 1 on and within NEAR_VESSEL_PX of the target's
    support, FAR_BACKGROUND_WEIGHT beyond."""
    support = (level_target > 1e-3).astype(np.uint8)
    size = 2 * NEAR_VESSEL_PX + 1
    near = cv2.dilate(support, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (size, size))) > 0
    return np.where(near, 1.0, FAR_BACKGROUND_WEIGHT).astype(np.float32)
