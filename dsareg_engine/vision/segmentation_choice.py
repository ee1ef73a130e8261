"""What ``auto`` segments a grey-level image with: the DSA border model or the angiogram network.

Two segmentations answer for grey images, each best where it was built for:

* ``dsa`` (:mod:`.dsa_border`, :mod:`.dsa_coverage`): a physical border model with sub-pixel borders; exact on
  clean subtracted DSA (ADD 0.005 mm on the paper's mesh), but on a real unsubtracted angiogram it marks
  background anatomy and the field's edge (median Dice 0.22 on real coronary angiograms);
* ``network`` (:mod:`.angiogram`): a U-Net trained on real angiograms; finds the vessels of real images
  (Dice 0.7+, cross-validated) with pixel-level borders.

``auto`` runs both and keeps ``dsa`` where the two agree (Dice of the masks ≥ ``AGREEMENT_DICE`` and at least
``EXPLAINED_SHARE`` of the ``dsa`` mask within 2 px of the network's: the image is one the border model reads
right, and its sub-pixel borders are kept), the network otherwise. Where they do not agree on the image as it is,
the network reads it once more after a flat-field correction (:mod:`.flat_field`: the smooth gain fitted on the
pixels neither mask holds, removed) and the choice is made on that reading: the border model subtracts its local
background and never sees such a gain, the network normalises the whole image and loses vessels where the field is
darker (a vignetted image intensifier, the heel effect), so only after the correction are the two compared on the
same image. The mask used when the network is chosen is the one of the image as it is. Where the image
has a collimated field, ``dsa`` is kept only inside it (the network's field, less its edge margin). Images that are
nearly two-level (≥ 90 % of the pixels within 10 % of the extremes: an anti-aliased or JPEG'd mask) keep the
``dsa`` path, whose histogram polarity reads masks of either polarity.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import cv2
import numpy as np

from .angiogram import AngiogramSegmentation, segment_angiogram

AGREEMENT_DICE = 0.5
"""The masks' Dice from which ``dsa`` may be kept. Measured (docs/benchmarks/segmentation.md): 0.62–0.86 on the
project's synthetic DSA (phantom and the paper's mesh, 512 and 800 px, nine image formations), 0.01–0.60 on the
40 real coronary angiograms (the network cross-validated; 5 of 40 above 0.5)."""
EXPLAINED_SHARE = 0.8
"""... and the share of the ``dsa`` mask within 2 px of the network's from which it is kept: 0.82–0.98 on that
synthetic DSA, at most 0.79 on those real angiograms (the border model's extra pixels there are background)."""
EXPLAINED_BAND = 0.02
"""A close call (the verdict at least ``check``) within this of :data:`EXPLAINED_SHARE`."""


@dataclass(frozen=True)
class AutoChoice:
    """Attributes:
        method: ``"dsa"`` or the angiogram method used (``"network"``, or ``"frangi"`` without weights).
        agreement: Dice of the two masks (None for mask-like images, where only ``dsa`` ran).
        dsa_mask: the ``dsa`` mask (H, W) bool. angiogram: the angiogram segmentation, or None.
        dsa_found: ``(contrast, noise σ, unrestricted mask)`` of the ``dsa`` path, for its coverage.
        inside: where a vessel may be (:func:`collimated_inside` of the network's field), None where only ``dsa`` ran.
        flat_field: ``agreement`` and ``explained`` are those of the network's reading after the flat-field
            correction (the image as it is did not agree).
    """

    method: str
    agreement: float | None
    dsa_mask: np.ndarray
    angiogram: AngiogramSegmentation | None
    explained: float | None = None
    dsa_found: tuple | None = None
    inside: np.ndarray | None = None
    flat_field: bool = False


def is_mask_like(pixels: np.ndarray) -> bool:
    """Nearly two-level: ≥ 90 % of the pixels within 10 % of the range from the minimum or the maximum."""
    low, high = float(pixels.min()), float(pixels.max())
    if high <= low:
        return True
    unit = (pixels.astype(np.float32) - low) / (high - low)
    return float(np.mean((unit <= 0.1) | (unit >= 0.9))) >= 0.9


def dice(first: np.ndarray, second: np.ndarray) -> float:
    total = int(first.sum()) + int(second.sum())
    return 1.0 if total == 0 else 2.0 * float((first & second).sum()) / total


def choose(pixels: np.ndarray, bright: np.ndarray, min_object_px: int, field: np.ndarray | None = None
           ) -> AutoChoice:
    """The ``auto`` choice for a grey image (``bright``: its vessels-bright form for ``dsa``)."""
    from .angiogram import network_usable
    from .dsa_coverage import dsa_found

    found = dsa_found(bright, min_object_px)
    dsa_mask = found[2]
    if is_mask_like(pixels) or not network_usable():
        return AutoChoice("dsa", None, dsa_mask, None, dsa_found=found)
    angiogram = segment_angiogram(pixels, field)
    inside = collimated_inside(angiogram.field)
    dsa_mask = dsa_mask & inside
    agreement, explained, flat = judged(pixels, dsa_mask, angiogram.mask, angiogram.field,
                                        lambda image: segment_angiogram(image, field).mask)
    method = "dsa" if agrees(agreement, explained) else angiogram.method
    return AutoChoice(method, round(agreement, 4), dsa_mask, angiogram, round(explained, 4), found, inside, flat)


def agrees(agreement: float, explained: float) -> bool:
    """The masks agree enough to keep ``dsa``: Dice ≥ :data:`AGREEMENT_DICE`, share ≥ :data:`EXPLAINED_SHARE`."""
    return agreement >= AGREEMENT_DICE and explained >= EXPLAINED_SHARE


def judged(pixels: np.ndarray, dsa_mask: np.ndarray, network_mask: np.ndarray, field: np.ndarray,
           segment: Callable[[np.ndarray], np.ndarray]) -> tuple[float, float, bool]:
    """``(Dice, explained share, flat-field)`` that ``auto`` decides on: those of ``network_mask`` (the network's
    mask of ``pixels``) where they agree (:func:`agrees`), else those of ``segment(flat-fielded pixels)`` (the
    network's mask of the image after :func:`~.flat_field.flat_fielded` on the pixels of ``field`` more than 2 px
    from either mask), where a correction could be fitted. ``segment``: image → the network's mask."""
    from .flat_field import flat_fielded

    agreement, explained = dice(dsa_mask, network_mask), explained_share(dsa_mask, network_mask)
    if agrees(agreement, explained):
        return agreement, explained, False
    corrected = flat_fielded(pixels, field & ~_near(dsa_mask | network_mask, 2), field)
    if corrected is None:
        return agreement, explained, False
    second = segment(corrected)
    return dice(dsa_mask, second), explained_share(dsa_mask, second), True


def _near(mask: np.ndarray, px: int) -> np.ndarray:
    return cv2.dilate(mask.astype(np.uint8), np.ones((2 * px + 1, 2 * px + 1), np.uint8)).astype(bool)


def explained_share(dsa_mask: np.ndarray, network_mask: np.ndarray) -> float:
    """The share of ``dsa_mask`` within 2 px of ``network_mask`` (both (H, W) bool)."""
    return float((dsa_mask & _near(network_mask, 2)).sum()) / max(int(dsa_mask.sum()), 1)


def collimated_inside(field: np.ndarray) -> np.ndarray:
    """Where a vessel may be: everywhere for an uncollimated image, else the field less its edge margin."""
    from .angiogram.field_of_view import inner_field
    from .angiogram.vessel_mask import edge_margin_px

    return field if field.all() else inner_field(field, edge_margin_px(field.shape))


def network_coverage(angiogram: AngiogramSegmentation) -> np.ndarray:
    """The registration target from an angiogram segmentation: the probability within 1 px of the mask (0
    elsewhere), float32 in [0, 1]: soft borders, no speckle outside the kept vessels."""
    near = cv2.dilate(angiogram.mask.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
    return np.where(near, angiogram.probability, 0.0).astype(np.float32)


def segmentation_decision(name: str, choice: AutoChoice):
    """The :class:`~dsareg_engine.io.input_decisions.InputDecision` of ``auto``'s choice for view ``name``: the
    share of the ``dsa`` mask the network explains against :data:`EXPLAINED_SHARE` (a close call within
    :data:`EXPLAINED_BAND`: the verdict says so), the masks' Dice named in the basis."""
    from ..io.input_decisions import InputDecision

    chosen = "dsa border model" if choice.method == "dsa" else f"angiogram {choice.method}"
    reading = " after a flat-field correction" if choice.flat_field else ""
    basis = (f"share of the dsa mask within 2 px of the network's{reading} (masks' Dice {choice.agreement:.2f}, "
             f"dsa kept from {AGREEMENT_DICE})")
    return InputDecision(name, "segmentation", chosen, basis, choice.explained, EXPLAINED_SHARE, EXPLAINED_BAND)
