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

Where they do not agree, ``dsa`` is still kept where its mask reads as a vessel tree and what it holds beyond the
network's is part of that tree (:func:`sparse_and_attached`): it covers at most ``SPARSE_COVERAGE`` of the field and
at least ``ATTACHED_SHARE`` of its pixels beyond 2 px of the network's mask lie in pieces joined to the part both
masks hold. On a small, foreshortened model the network misses thin distal branches and overlapping segments (and
keeps the catheter, which the model lacks): the border model's extra pixels are then the branches the network
missed, joined to the tree, and its mask covers ~1 % of the field. On an unsubtracted angiogram the border model's
extra pixels are background anatomy and the field's edge, and its mask covers 12 % of the field or more.
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
SPARSE_COVERAGE = 0.05
"""Where the masks do not agree, ``dsa`` is kept if its mask covers at most this share of the field (the collimated
inside) ... Measured (docs/benchmarks/segmentation.md): on the project's synthetic grey DSA (phantom and the paper's
mesh; paper rig 800 px, clinical rig 512 / 1024 px at the identity pose and ``random_visible_pose`` seeds 0–4; the
nine formations; 325 views) 0.006–0.019 on the 26 views where the masks disagree, 0.006–0.034 on all but the paper's
mesh at 800 px (0.056–0.075, where they all agree); 0.116–0.930 on the 40 real coronary angiograms (the border model
marks background anatomy; the network cross-validated)."""
SPARSE_BAND = 0.01
"""A close call within this of :data:`SPARSE_COVERAGE`."""
ATTACHED_SHARE = 0.9
"""... and at least this share of the ``dsa`` pixels beyond 2 px of the network's mask lie in ``dsa`` components that
hold a pixel both masks hold (the extra pixels are branches of the same tree, not detached blobs). Measured on that
synthetic DSA where the masks disagree: 1.000 on 24 of 26 views (missed branches: the phantom at foreshortened
poses), 0.089 and 0.417 where they are detached background blobs (``background_fine``: the network kept); on the
real angiograms 0.33–1.00 (the coverage decides there)."""


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
        coverage, attached: :func:`sparse_and_attached` of the masks decided on, where they did not agree (else None);
            ``dsa`` was kept on them where ``method`` is ``"dsa"`` and :func:`agrees` is False.
    """

    method: str
    agreement: float | None
    dsa_mask: np.ndarray
    angiogram: AngiogramSegmentation | None
    explained: float | None = None
    dsa_found: tuple | None = None
    inside: np.ndarray | None = None
    flat_field: bool = False
    coverage: float | None = None
    attached: float | None = None


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
    agreement, explained, flat, network_mask = judged_reading(pixels, dsa_mask, angiogram.mask, angiogram.field,
                                                              lambda image: segment_angiogram(image, field).mask)
    coverage = attached = None
    if not agrees(agreement, explained):
        coverage, attached = (round(value, 4) for value in sparse_and_attached(dsa_mask, network_mask, inside))
    method = "dsa" if keeps_dsa(agreement, explained, coverage, attached) else angiogram.method
    return AutoChoice(method, round(agreement, 4), dsa_mask, angiogram, round(explained, 4), found, inside, flat,
                      coverage, attached)


def agrees(agreement: float, explained: float) -> bool:
    """The masks agree enough to keep ``dsa``: Dice ≥ :data:`AGREEMENT_DICE`, share ≥ :data:`EXPLAINED_SHARE`."""
    return agreement >= AGREEMENT_DICE and explained >= EXPLAINED_SHARE


def keeps_dsa(agreement: float, explained: float, coverage: float | None, attached: float | None) -> bool:
    """``dsa`` is kept: the masks agree (:func:`agrees`), or its mask is sparse (``coverage`` ≤
    :data:`SPARSE_COVERAGE`) and its extra pixels attached to the shared tree (``attached`` ≥ :data:`ATTACHED_SHARE`)."""
    if agrees(agreement, explained):
        return True
    return (coverage is not None and attached is not None and coverage <= SPARSE_COVERAGE
            and attached >= ATTACHED_SHARE)


def sparse_and_attached(dsa_mask: np.ndarray, network_mask: np.ndarray, inside: np.ndarray) -> tuple[float, float]:
    """``(coverage, attached)``: the share of ``inside`` (the field) that ``dsa_mask`` covers, and the share of its
    pixels beyond 2 px of ``network_mask`` that lie in 8-connected components of ``dsa_mask`` holding a pixel within
    2 px of it (1.0 where there are none)."""
    from scipy import ndimage

    explained = dsa_mask & _near(network_mask, 2)
    extra = dsa_mask & ~explained
    coverage = float(dsa_mask.sum()) / max(int(inside.sum()), 1)
    if not extra.any():
        return coverage, 1.0
    labels, _ = ndimage.label(dsa_mask, structure=np.ones((3, 3), bool))
    joined = np.zeros(int(labels.max()) + 1, bool)
    joined[np.unique(labels[explained])] = True
    joined[0] = False
    return coverage, float(joined[labels[extra]].sum()) / int(extra.sum())


def judged(pixels: np.ndarray, dsa_mask: np.ndarray, network_mask: np.ndarray, field: np.ndarray,
           segment: Callable[[np.ndarray], np.ndarray]) -> tuple[float, float, bool]:
    """``(Dice, explained share, flat-field)`` that ``auto`` decides on: those of ``network_mask`` (the network's
    mask of ``pixels``) where they agree (:func:`agrees`), else those of ``segment(flat-fielded pixels)`` (the
    network's mask of the image after :func:`~.flat_field.flat_fielded` on the pixels of ``field`` more than 2 px
    from either mask), where a correction could be fitted. ``segment``: image → the network's mask."""
    return judged_reading(pixels, dsa_mask, network_mask, field, segment)[:3]


def judged_reading(pixels: np.ndarray, dsa_mask: np.ndarray, network_mask: np.ndarray, field: np.ndarray,
                   segment: Callable[[np.ndarray], np.ndarray]) -> tuple[float, float, bool, np.ndarray]:
    """:func:`judged` and the network's mask it was measured on."""
    from .flat_field import flat_fielded

    agreement, explained = dice(dsa_mask, network_mask), explained_share(dsa_mask, network_mask)
    if agrees(agreement, explained):
        return agreement, explained, False, network_mask
    corrected = flat_fielded(pixels, field & ~_near(dsa_mask | network_mask, 2), field)
    if corrected is None:
        return agreement, explained, False, network_mask
    second = segment(corrected)
    return dice(dsa_mask, second), explained_share(dsa_mask, second), True, second


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
    :data:`EXPLAINED_BAND`: the verdict says so), the masks' Dice named in the basis; where ``dsa`` was kept on a
    sparse, attached mask the masks did not agree on (:func:`keeps_dsa`), its coverage of the field against
    :data:`SPARSE_COVERAGE` (band :data:`SPARSE_BAND`), the attached share, explained share and Dice in the basis."""
    from ..io.input_decisions import InputDecision

    chosen = "dsa border model" if choice.method == "dsa" else f"angiogram {choice.method}"
    reading = " after a flat-field correction" if choice.flat_field else ""
    if choice.method == "dsa" and choice.coverage is not None:
        basis = (f"share of the field the dsa mask covers, dsa kept at most {SPARSE_COVERAGE} (a sparse tree; "
                 f"{choice.attached:.2f} of its pixels beyond 2 px of the network's{reading} joined to the shared "
                 f"part, from {ATTACHED_SHARE}; share within 2 px {choice.explained:.2f}, masks' Dice "
                 f"{choice.agreement:.2f})")
        return InputDecision(name, "segmentation", chosen, basis, choice.coverage, SPARSE_COVERAGE, SPARSE_BAND)
    basis = (f"share of the dsa mask within 2 px of the network's{reading} (masks' Dice {choice.agreement:.2f}, "
             f"dsa kept from {AGREEMENT_DICE})")
    return InputDecision(name, "segmentation", chosen, basis, choice.explained, EXPLAINED_SHARE, EXPLAINED_BAND)
