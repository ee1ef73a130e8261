"""Which view sees a vessel point clear of other vessels.

A point is **overlapped** in a view when another part of the model lies across its footprint (the vessel's
projected cross-section, :mod:`.sampling`) at a different depth. Per pixel, the rays are traced through the
model at the pose (:func:`dsareg_engine.render.ray_layers.layer_counts`): a ray that crosses two or more separate
parts of the model (stretches with a gap between them along the ray) sees vessels at different depths. A point
whose footprint has at least ``OVERLAP_SHARE`` of its pixels on such rays is overlapped: its curve there mixes
two vessels' contrast, so the other view carries it.

The test is at the scale of the vessel's own cross-section and uses the model itself, not vertex neighbourhoods:
a vessel passing beside the footprint does not flag it, nor does the same vessel running on (one stretch), nor a
bifurcation (the stretches join).
"""

from __future__ import annotations

import numpy as np

from .sampling import Footprints

OVERLAP_SHARE = 0.2


def overlapped(prints: Footprints, layers: np.ndarray) -> np.ndarray:
    """``(N,)`` bool from the footprints of one view and its per-pixel layer counts ``(H, W)``."""
    share = prints.footprint @ (layers >= 2).ravel().astype(np.float64)
    return np.asarray(share >= OVERLAP_SHARE)
