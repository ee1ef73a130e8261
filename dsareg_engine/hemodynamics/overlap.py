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


def _candidates(uv: np.ndarray, reach: np.ndarray, r_px: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(i, j)`` pairs that may touch (``|uv_i − uv_j| < reach_i + r_px_j``): every ``i`` searched out to its reach
    plus the usual radius, and the few thicker ``j`` searched from their side."""
    tree = cKDTree(uv)
    usual = float(np.percentile(r_px, 95))
    found = tree.query_ball_point(uv, reach + usual, return_sorted=False)
    first = [np.full(len(x), i) for i, x in enumerate(found)]
    second = [np.asarray(x, int) for x in found]
    for j in np.flatnonzero(r_px > usual):
        near = np.asarray(tree.query_ball_point(uv[j], r_px[j] + float(reach.max())), int)
        first.append(near)
        second.append(np.full(len(near), j))
    return np.concatenate(first).astype(int), np.concatenate(second).astype(int)


def overlapped(projection: Projection, centres_mm: np.ndarray, radii_mm: np.ndarray) -> np.ndarray:
    """``(N,)`` bool: the points another model part overlaps in this view (points outside the image: False)."""
    flags = np.zeros(len(radii_mm), bool)
    inside = np.flatnonzero(projection.inside)
    if len(inside) < 2:
        return flags
    uv = projection.uv_px[inside]
    reach = projection.footprint_px[inside]
    r_px = projection.radius_px[inside]
    first, second = _candidates(uv, reach, r_px)
    touching = np.linalg.norm(uv[first] - uv[second], axis=1) < reach[first] + r_px[second]
    a, b = inside[first], inside[second]
    apart = np.linalg.norm(centres_mm[a] - centres_mm[b], axis=1) > SAME_PART_RADII * (radii_mm[a] + radii_mm[b])
    flags[a[touching & apart]] = True
    return flags
