"""Border correction: how much wider the segmented vessels are than the model's outline.

A vessel mask thresholded from a DSA image rarely has its border exactly where the model's
surface projects; a mask drawn b px wider all round holds about b × perimeter more pixels.
A silhouette fit then explains part of that excess by moving the mesh toward the source
(magnification), a bias of ~0.2–0.3 mm per pixel on the paper's mesh at 800 px. Shifting the
target's border by the measured excess before the fine stages removes it; the two views'
positions, not their widths, then fix the depth.
"""

from __future__ import annotations

import cv2
import numpy as np

from ..metrics import within_px
from .targets import mask_box, shifted_mask, signed_border_distance

_CROSS = cv2.getStructuringElement(cv2.MORPH_CROSS, (3, 3))

MAX_BORDER_SHIFT_PX = 2.0
"""Largest correction (full-resolution px, either sign): beyond it the mismatch is not a border."""
BAND_PX = 3.0
"""Pixels farther than this from the other outline are structures of their own, not border."""


_OUTLINE_WEIGHTS = np.zeros(50)
_OUTLINE_WEIGHTS[[5, 7, 15, 17, 25, 27]] = 1.0
_OUTLINE_WEIGHTS[[21, 33]] = np.sqrt(2.0)
_OUTLINE_WEIGHTS[[13, 23]] = (1.0 + np.sqrt(2.0)) / 2.0
_OUTLINE_CODES = np.array([[10, 2, 10], [2, 1, 2], [10, 2, 10]], dtype=np.float32)


def outline_length_px(boundary: np.ndarray) -> float:
    """Length (px) of an outline given as its 4-connected boundary pixels ``(H, W)`` bool.

    Benkrid & Crookes' estimator — each boundary pixel weighted by the pattern of its boundary
    neighbours — as ``skimage.measure.perimeter`` computes it (the same numbers), by OpenCV.
    """
    codes = cv2.filter2D(boundary.astype(np.uint8), cv2.CV_32F, _OUTLINE_CODES, borderType=cv2.BORDER_CONSTANT)
    return float(np.bincount(codes.astype(np.int64).ravel(), minlength=50)[:50] @ _OUTLINE_WEIGHTS)


def update_border_shift(mask: np.ndarray, silhouette: np.ndarray, shift_px: float, signed: np.ndarray | None = None) -> float:
    """One area-matching update of the target's border shift.

    Only pixels within BAND_PX of both outlines count: vessels the mask has and the model
    lacks (or the reverse), catheters and speckle away from the model are not border errors.

    Args:
        mask: ``(H, W)`` target at full resolution: bool mask, or float coverage in [0, 1].
        silhouette: ``(H, W)`` bool hard silhouette of the model at the current pose, same size.
        shift_px: the shift in use (0 at first).
        signed: :func:`~.targets.signed_border_distance` of ``mask`` (computed when not given).

    Returns:
        The new shift (px, positive = move the target's border outward), clamped to
        ±MAX_BORDER_SHIFT_PX; unchanged when nothing of the two lies near the other.
    """
    if signed is None:
        signed = signed_border_distance(mask)
    # Everything below happens within BAND_PX + MAX_BORDER_SHIFT_PX of the two outlines: the box around
    # both (plus a margin) gives the same sums as the whole image at a fraction of the cost.
    box = mask_box((mask, silhouette), int(np.ceil(BAND_PX + MAX_BORDER_SHIFT_PX)) + 2)
    if box is None:
        return shift_px
    mask, silhouette, signed = mask[box], silhouette[box], signed[box]
    target = shifted_mask(mask, shift_px, signed)
    near_silhouette = within_px(silhouette, BAND_PX)
    near_target = signed <= shift_px + BAND_PX - 0.5  # within BAND_PX of a pixel of the shifted target
    boundary = silhouette & (cv2.erode(silhouette.astype(np.uint8), _CROSS, borderValue=0) == 0)
    if not boundary.any():
        return shift_px
    shared_outline = outline_length_px(boundary) * (boundary & near_target).sum() / boundary.sum()
    if shared_outline < 1.0:
        return shift_px
    excess = float((target * near_silhouette).sum() - (silhouette & near_target).sum())
    return float(np.clip(shift_px - excess / shared_outline, -MAX_BORDER_SHIFT_PX, MAX_BORDER_SHIFT_PX))
