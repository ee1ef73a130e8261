"""Which view sees a vessel point clear of other vessels.

A point is **overlapped** in a view when another part of the model lies across its footprint at a different
depth: a vessel point ``j`` whose projected cross-section reaches into the point's footprint
(``|uv_j − uv_i| < ρ_i + r_px_j``; ``ρ`` the footprint radius, :mod:`.sampling`) while in 3D it is not the same
stretch of vessel (``|c_j − c_i| > SAME_PART_RADII · (r_i + r_j)``: farther than the two cross-sections could
be if they touched). The test is at the scale of the vessel's own projected cross-section, not "anything
nearby": a neighbouring vessel beside the footprint does not flag it; the same vessel running on does not.
Such a view's curve mixes two vessels' contrast, so the other view carries the point.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from .sampling import Projection

SAME_PART_RADII = 2.0


def overlapped(projection: Projection, centres_mm: np.ndarray, radii_mm: np.ndarray) -> np.ndarray:
    """``(N,)`` bool: the points another model part overlaps in this view (points outside the image: False)."""
    count = len(radii_mm)
    flags = np.zeros(count, bool)
    inside = np.flatnonzero(projection.inside)
    if len(inside) < 2:
        return flags
    uv = projection.uv_px[inside]
    reach = projection.footprint_px[inside]
    r_px = projection.radius_px[inside]
    found = cKDTree(uv).query_ball_point(uv, reach + float(r_px.max()), return_sorted=False)
    lengths = np.fromiter((len(x) for x in found), int, len(found))
    first = np.repeat(np.arange(len(inside)), lengths)
    second = np.fromiter((j for x in found for j in x), int, int(lengths.sum()))
    planar = np.linalg.norm(uv[first] - uv[second], axis=1)
    touching = planar < reach[first] + r_px[second]
    a, b = inside[first], inside[second]
    apart = np.linalg.norm(centres_mm[a] - centres_mm[b], axis=1) > SAME_PART_RADII * (radii_mm[a] + radii_mm[b])
    hit = touching & apart
    flags[a[hit]] = True
    return flags
