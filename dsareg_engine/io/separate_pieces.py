"""Separate pieces of a CTA / TOF-MRA reading that are not arteries: blocks of bone and dural venous sinuses.

A reading's separate pieces of at least ``PIECE_MM3`` are measured against what bone lies against (``bone_of``)
twice: the share of their surface voxels touching bone (:func:`.bone_plates.contact_shares`) and how far their
medial axis runs with the lumen against bone, and how thick they are (:func:`.venous_sinuses.along_bone`). A
piece that runs along bone (``ALONG_BONE_SHARE``) is set aside:

* **in bone** when half its surface or more touches bone (``BONE_CONTACT_SHARE``): a block of cancellous bone (a
  clivus, a petrous apex, a marrow space) is thick, not a plate, and its interior lies far enough from the cortex
  around it to be read as vessel; cortex and its band enclose it (surface ~0.95–1). A vessel whose trunk lies in a
  bony canal can have half its surface against bone too, but its axis leaves the bone: it stays.
* a **venous sinus** when thick (``SINUS_RADIUS_MM``): a dural sinus runs with its lumen against the skull's inner
  table along its whole course (a CTA with venous filling); it touches bone on one side only.

A thick piece along bone goes whatever its surface's share: it is no close call of that share; a block of bone is
no close call of the sinuses' measure. When next to nothing would stay (under ``KEPT_SHARE_MIN`` of the voxels:
specks), the reading is kept as it is (and judged as it is); a small tree beside a large venous system stays alone
(on a third generator's head: 4 % of the voxels). :func:`.volume_vessels._tubes` reads the volume again without the pieces in the vessels' level estimate.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .bone_plates import BONE_CONTACT_SHARE, PLATE_PART_MM3, contact_shares
from .venous_sinuses import ALONG_BONE_SHARE, SINUS_RADIUS_MM, along_bone_of
from .voxel_steps import bounding_box, label_sizes, labelled, map_labels

PIECE_MM3 = PLATE_PART_MM3  # a smaller piece is not judged: too small to be a bone block or to mislead a registration
KEPT_SHARE_MIN = 0.02  # what would stay under this share of the voxels (specks): nothing is set aside


@dataclass(frozen=True)
class PiecesSetAside:
    """The separate pieces one measure (its ``threshold``) set aside (:func:`without_pieces`): how many, their voxels
    (bool, the mask's shape; None when none) and the measures of the pieces it judged: kept and set aside."""

    threshold: float
    count: int = 0
    set_aside: np.ndarray | None = None
    kept_shares: tuple[float, ...] = ()
    set_aside_shares: tuple[float, ...] = ()

    @property
    def nearest_share(self) -> float | None:
        """The judged piece's measure nearest the threshold on either side (the decision's margin); None when the
        measure judged no piece."""
        shares = np.array(self.kept_shares + self.set_aside_shares, float)
        return None if len(shares) == 0 else float(shares[np.argmin(np.abs(shares - self.threshold))])

    def then(self, later: PiecesSetAside) -> PiecesSetAside:
        """This record followed by a later reading's (without this one's pieces): the pieces both set aside, and the
        pieces the later one kept (those this one kept are read again)."""
        return PiecesSetAside(self.threshold, self.count + later.count, later.set_aside, later.kept_shares,
                              self.set_aside_shares + later.set_aside_shares)


def without_pieces(mask: np.ndarray, spacing: np.ndarray, bone_of) -> tuple[np.ndarray, dict[str, PiecesSetAside]]:
    """``mask`` without its separate pieces in bone and its venous sinuses, and the two records (``bone``,
    ``sinuses``). ``bone_of(box)``: bool, what bone lies where ``mask[box]`` lies (CTA: bone and its partial-volume
    band beyond the reading's voxels; TOF-MRA: the voids and the scalp shell)."""
    records = {"bone": PiecesSetAside(BONE_CONTACT_SHARE), "sinuses": PiecesSetAside(ALONG_BONE_SHARE)}
    box = bounding_box(mask, margin=1)
    if box is None:
        return mask, records
    labels, count = labelled(mask[box], narrow_above=0)
    if count < 2:
        return mask, records
    bone = np.ascontiguousarray(bone_of(box))
    contact = contact_shares(labels, range(1, count + 1), bone)
    sizes = label_sizes(labels, count, mask[box])[1:]
    large = sizes * float(np.prod(spacing)) >= PIECE_MM3
    along = np.full(count, np.nan)  # the along-bone share of the thick pieces (a thinner one's decides nothing)
    runs_along = np.zeros(count, bool)
    either = np.zeros(count, bool)  # thick and along bone: set aside by either measure
    judged = np.flatnonzero(large)
    for index, measure in zip(judged, along_bone_of(labels, judged + 1, bone, spacing)):
        runs_along[index], either[index] = measure.share >= ALONG_BONE_SHARE, measure.sinus
        if measure.radius_mm >= SINUS_RADIUS_MM:
            along[index] = measure.share
    in_bone = runs_along & (contact >= BONE_CONTACT_SHARE)  # enclosed, all along: a block of bone
    sinus = either & ~in_bone
    del bone
    if sizes[~(in_bone | sinus)].sum() < KEPT_SHARE_MIN * sizes.sum():  # next to nothing would stay: the reading
        in_bone[:], sinus[:] = False, False  # is judged as it is
    out = mask.copy() if (in_bone | sinus).any() else mask
    for name, chosen, shares, others in (("bone", in_bone, contact, either), ("sinuses", sinus, along, in_bone)):
        set_aside = None
        if chosen.any():
            set_aside = np.zeros(mask.shape, bool)
            map_labels(set_aside[box], np.concatenate([[False], chosen]), labels)
            out &= ~set_aside
        judged = ~others & ~np.isnan(shares)
        records[name] = PiecesSetAside(records[name].threshold, int(chosen.sum()), set_aside,
                                       tuple(shares[judged & ~chosen]), tuple(shares[judged & chosen]))
    return out, records


__all__ = ["KEPT_SHARE_MIN", "PIECE_MM3", "PiecesSetAside", "without_pieces"]
