"""A view's square search window around its vessel mask: one crop for the centroid and the coverage searches.

The window is ``side_px`` detector pixels wide (before scaling), centred on the mask's bounding box, scaled so it is
at most ``window_px`` wide; its side is rounded to a multiple of ``multiple`` px. Pixels past the detector's edge are
zero in ``coverage``; ``corner_px`` says where the window starts on the scaled detector (they may be negative).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from ...geometry.rig import ViewGeometry


@dataclass(frozen=True)
class MaskWindow:
    view: ViewGeometry  # the window as a view of its own (principal point moved to the window's origin)
    coverage: np.ndarray  # (S, S) float32: the mask's area coverage on the scaled detector, cropped
    corner_px: tuple[int, int]  # (column, row) of the window's origin on the scaled detector
    level: ViewGeometry  # the whole detector at the window's scale


def mask_window(view: ViewGeometry, mask: np.ndarray, side_px: float, window_px: float,
                multiple: int = 1) -> MaskWindow:
    """The window of ``mask`` ``(H, W)`` bool in ``view``; ``side_px`` in ``view``'s own pixels."""
    rows, cols = np.nonzero(mask)
    level = view.scaled(min(1.0, window_px / side_px))
    pixel_scale = level.width / view.width
    side = int(multiple * round(side_px * pixel_scale / multiple))
    centre = np.array([(cols.max() + cols.min()) / 2.0, (rows.max() + rows.min()) / 2.0])
    corner = np.round(pixel_scale * (centre + 0.5) - 0.5 - side / 2.0)
    u0, v0 = level.principal_point_px
    window_view = ViewGeometry((side, side), level.pixel_spacing_mm, level.sid_mm,
                               (u0 - corner[0], v0 - corner[1]), level.world_to_view)
    scaled = cv2.resize(mask.astype(np.float32), level.image_size, interpolation=cv2.INTER_AREA)
    coverage = np.zeros((side, side), np.float32)
    c0, r0 = int(corner[0]), int(corner[1])
    src = scaled[max(r0, 0): r0 + side, max(c0, 0): c0 + side]
    coverage[max(-r0, 0): max(-r0, 0) + src.shape[0], max(-c0, 0): max(-c0, 0) + src.shape[1]] = src
    return MaskWindow(window_view, coverage, (c0, r0), level)


def mask_extent_px(mask: np.ndarray) -> float:
    """The larger side of ``mask``'s bounding box, px (inclusive)."""
    rows, cols = np.nonzero(mask)
    return max(cols.max() - cols.min(), rows.max() - rows.min()) + 1.0
