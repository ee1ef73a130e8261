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

from ..metrics import within_px

MATCH_TOLERANCE_PX = 2.0
NEAR_VESSEL_PX = 2
FAR_BACKGROUND_WEIGHT = 0.05
PARTIAL_UNMATCHED = 0.1
"""Partial visibility: at least this fraction of the model's silhouette unmatched in every view..."""
PARTIAL_UNCOVERED = 0.05
"""... while at most this fraction of the vessels is uncovered in every view."""
PART_UNEXPLAINED = 0.01
"""A fitted part (:mod:`.search.branch_search`) with more than this share of its faces off the vessels at its fitted
pose is fitted once more on the faces the images explain (:func:`refit_faces`)."""


def _near(mask: np.ndarray, tolerance_px: float) -> np.ndarray:
    return within_px(mask, tolerance_px)


def match_fractions(silhouette: np.ndarray, mask: np.ndarray, tolerance_px: float = MATCH_TOLERANCE_PX,
                    mask_near: np.ndarray | None = None) -> dict:
    """``{"unmatched": …, "uncovered": …}`` of one view (see the module); 1.0 where the silhouette / mask is empty.
    ``mask_near``: ``_near(mask, tolerance_px)`` when the caller keeps it."""
    return {"unmatched": _unmatched(silhouette, mask, tolerance_px, mask_near), "uncovered": _uncovered(silhouette, mask, tolerance_px)}


def _unmatched(silhouette: np.ndarray, mask: np.ndarray, tolerance_px: float, mask_near: np.ndarray | None = None) -> float:
    if not silhouette.any():
        return 1.0
    near = _near(mask, tolerance_px) if mask_near is None else mask_near
    return float((silhouette & ~near).sum() / silhouette.sum())


def _uncovered(silhouette: np.ndarray, mask: np.ndarray, tolerance_px: float) -> float:
    return float((mask & ~_near(silhouette, tolerance_px)).sum() / mask.sum()) if mask.any() else 1.0


def view_looks_partial(silhouette: np.ndarray, mask: np.ndarray, mask_near: np.ndarray | None = None,
                       tolerance_px: float = MATCH_TOLERANCE_PX) -> bool:
    """One view's part of :func:`looks_partial`, the same answer as from :func:`match_fractions`, but the uncovered
    fraction (a distance transform of the silhouette) only computed when the unmatched one qualifies."""
    if _unmatched(silhouette, mask, tolerance_px, mask_near) < PARTIAL_UNMATCHED:
        return False
    return _uncovered(silhouette, mask, tolerance_px) <= PARTIAL_UNCOVERED


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


def explained_faces(mesh, mesh_to_world: np.ndarray, masks: dict[str, np.ndarray], rig,
                    tolerance_px: float = MATCH_TOLERANCE_PX) -> np.ndarray:
    """``(F,)`` bool: the faces of ``mesh`` whose centroid projects within ``tolerance_px`` of the vessels of every
    view in ``masks`` (``(H, W)`` bool) at ``mesh_to_world`` — what of the model the images show."""
    centroids = mesh.vertices[mesh.faces].mean(axis=1) @ mesh_to_world[:3, :3].T + mesh_to_world[:3, 3]
    explained = np.ones(mesh.n_faces, bool)
    for name, mask in masks.items():
        pixel = np.floor(rig.views[name].project(centroids) + 0.5).astype(np.int64)
        height, width = mask.shape
        inside = (pixel[:, 0] >= 0) & (pixel[:, 0] < width) & (pixel[:, 1] >= 0) & (pixel[:, 1] < height)
        near = _near(mask, tolerance_px)
        explained &= inside & near[np.clip(pixel[:, 1], 0, height - 1), np.clip(pixel[:, 0], 0, width - 1)]
    return explained


def refit_faces(part: np.ndarray, explained: np.ndarray, min_faces: int = 50) -> np.ndarray | None:
    """The faces to fit once more after a part ``(F,)`` bool was fitted, given the faces the images explain at its
    pose ``(F,)`` bool: those explained faces when more than :data:`PART_UNEXPLAINED` of the part lies off the
    vessels (the part holds something the run did not fill: on a model of two trees joined at the inflow, a stub of
    the other tree's trunk pulled the fit 0.9° off) and at least half the part and ``min_faces`` are explained (else
    the pose itself is in doubt, which the verdict says); None otherwise."""
    off_vessels = (part & ~explained).sum()
    if off_vessels <= PART_UNEXPLAINED * part.sum() or explained.sum() < max(min_faces, 0.5 * part.sum()):
        return None
    return explained
