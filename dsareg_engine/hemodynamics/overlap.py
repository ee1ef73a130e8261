"""Which view sees a vessel point clear of other vessels.

A point is **overlapped** in a view when another part of the model lies across its footprint (the vessel's
projected cross-section, :mod:`.sampling`). Two ways, both at the scale of the vessel's own cross-section and
both from the model itself:

* **in depth** (:func:`overlapped`): per pixel, the rays are traced through the model at the pose
  (:func:`dsareg_engine.render.ray_layers.layer_counts`); a ray that crosses two or more separate parts of the
  model (stretches with a gap between them along the ray) sees vessels at different depths. A footprint with at
  least ``OVERLAP_SHARE`` of its pixels on such rays is overlapped;
* **beside** (:func:`foreign_share`): a footprint whose rays partly miss the point's own vessel and cross
  another one (a thin vessel whose footprint, at least ``MIN_FOOTPRINT_PX`` wide, reaches past its walls onto a
  vessel running beside it in the image, at any depth): each stretch a ray crosses is owned by the vessel point
  nearest its middle (:func:`.unmixing.stretch_owners`), and a stretch is **foreign** to point ``i`` when its
  owner ``j`` lies farther than ``OWN_VESSEL_RADII · (r_i + r_j)`` from it (two separate vessels' walls meet at
  ``r_i + r_j``; the margin is for radii estimated from the mesh; its own vessel's points, along its axis within
  the footprint and round its wall, and a bifurcation's, lie within it). A footprint with
  at least ``OVERLAP_SHARE`` of its path (mm) foreign is overlapped.

Either way its curve there is mostly another vessel's contrast: the other view carries the point, or it is
unmixed (:mod:`.unmixing`), with its own vessel's share of the path (``own_path_mm``) as its own evidence.
A vessel passing beside the footprint without entering it flags nothing, nor does the same vessel running on.
"""

from __future__ import annotations

import numpy as np
from scipy import sparse

from .sampling import Footprints

OVERLAP_SHARE = 0.2
OWN_VESSEL_RADII = 1.5


def overlapped(prints: Footprints, layers: np.ndarray) -> np.ndarray:
    """``(N,)`` bool from the footprints of one view and its per-pixel layer counts ``(H, W)``."""
    share = prints.footprint @ (layers >= 2).ravel().astype(np.float64)
    return np.asarray(share >= OVERLAP_SHARE)


def own_path_mm(mixing: sparse.csr_matrix, centres_mm: np.ndarray, radii_mm: np.ndarray) -> np.ndarray:
    """``(N,)`` the footprint's mean path (mm) through its own vessel: the entries of ``mixing`` ``(N, N)`` (mm, row
    = footprint, column = owner) whose owner lies within ``OWN_VESSEL_RADII · (r_i + r_j)`` of the point."""
    entries = mixing.tocoo()
    distance = np.linalg.norm(centres_mm[entries.row] - centres_mm[entries.col], axis=1)
    own = distance <= OWN_VESSEL_RADII * (radii_mm[entries.row] + radii_mm[entries.col])
    return np.bincount(entries.row[own], weights=entries.data[own], minlength=mixing.shape[0])


def foreign_share(mixing: sparse.csr_matrix, own_mm: np.ndarray) -> np.ndarray:
    """``(N,)`` the share of each footprint's path that other vessels own (0 where the footprint crosses none)."""
    path = np.asarray(mixing.sum(axis=1)).ravel()
    return np.where(path > 0, 1.0 - own_mm / np.maximum(path, 1e-12), 0.0)
