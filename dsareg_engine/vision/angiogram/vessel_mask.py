"""A vessel probability ``(H, W)`` → the binary vessel mask of a real X-ray angiogram.

* pixels at probability ≥ ``threshold`` (0.5: the network's own decision, not tuned on any scored image);
* nothing within ``edge_margin`` of the field of view's edge (the collimator's edge is no vessel; the margin is
  ~1 % of the image side, 3 px at 300 px);
* pieces smaller than ``min_piece_fraction`` of the field removed (speckle, dust), and pieces lying along the
  field's edge (at least half of the piece within ``edge_band_margins`` margins of it): a vessel crosses the
  edge, the edge's own ring runs along it; for the same reason, within that band, the parts of a piece that
  run along the edge (their box longer than three band widths) are cut off the vessel they touch;
* at most ``max_coverage`` of the field: a mask covering more is not a vessel tree (a cerebral or coronary tree
  covers 3–15 % of a field); the most probable pixels are kept up to that share and the cut recorded.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from .field_of_view import inner_field


@dataclass(frozen=True)
class MaskSettings:
    """Attributes: see the module docstring."""

    threshold: float = 0.5
    edge_margin_fraction: float = 0.01
    min_piece_fraction: float = 2e-4
    max_coverage: float = 0.25
    edge_band_margins: int = 3


def edge_margin_px(shape: tuple[int, int], settings: MaskSettings = MaskSettings()) -> int:
    return max(2, int(round(settings.edge_margin_fraction * max(shape))))


def vessel_mask(probability: np.ndarray, field: np.ndarray, settings: MaskSettings = MaskSettings()
                ) -> tuple[np.ndarray, dict]:
    """``(mask (H, W) bool, what was done)`` from ``probability`` and the field of view ``field`` (True inside)."""
    inside = inner_field(field, edge_margin_px(field.shape, settings))
    mask = (probability >= settings.threshold) & inside
    area = max(int(inside.sum()), 1)
    threshold = settings.threshold
    if mask.sum() > settings.max_coverage * area:
        threshold = float(np.quantile(probability[inside], 1.0 - settings.max_coverage))
        mask = (probability > threshold) & inside
    labels, count = ndimage.label(mask, structure=np.ones((3, 3), bool))
    sizes = np.bincount(labels.ravel(), minlength=count + 1)
    band = field & ~inner_field(field, settings.edge_band_margins * edge_margin_px(field.shape, settings))
    in_band = np.bincount(labels[band].ravel(), minlength=count + 1)
    dropped = (sizes < max(4, settings.min_piece_fraction * area)) | (2 * in_band >= sizes)
    dropped[0] = False
    mask &= ~dropped[labels]
    mask &= ~_along_the_edge(mask & band, 3 * settings.edge_band_margins * edge_margin_px(field.shape, settings))
    return mask, {"threshold": round(threshold, 3), "removed_pieces": int(dropped.sum()),
                  "edge_margin_px": edge_margin_px(field.shape, settings),
                  "coverage_of_field": round(float(mask.sum()) / area, 4)}


def _along_the_edge(in_band: np.ndarray, max_extent_px: int) -> np.ndarray:
    """The pieces of ``in_band`` (the mask within the field's edge band) whose box is longer than
    ``max_extent_px`` on a side: they run along the edge (a vessel crossing the band spans about its width)."""
    labels, count = ndimage.label(in_band, structure=np.ones((3, 3), bool))
    along = np.zeros(count + 1, bool)
    for index, box in enumerate(ndimage.find_objects(labels), start=1):
        if box is not None and max(box[0].stop - box[0].start, box[1].stop - box[1].start) > max_extent_px:
            along[index] = True
    return along[labels]
