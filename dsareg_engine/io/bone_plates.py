"""Which plate parts of a vessel reading are bone (issue 41: the diploë and the skull base of a whole-head CTA).

The medial measure (:mod:`.medial_shape`) finds the plate-shaped parts of the voxels read as vessels; a part is
set aside as bone when it is bone-sized (at least ``PLATE_PART_MM3``) and bone-placed (at least
``BONE_CONTACT_SHARE`` of its surface voxels touch what bone lies against). A vessel tree's plate-like stretches
(close-packed loops, a bulge) are smaller or lie in tissue, and stay with the tree.

A reading's mask is measured by :func:`plates_found` and cleaned by :func:`without_plates` (the plates, their rim
and fragments removed, the largest tube components kept); the reading that is read again (its level estimated
without the plates) cleans only its last mask.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .medial_shape import medial_shape
from .vessel_shape import MAX_PLATE_FRACTION, PLATE_BAND
from .volume_io import largest_components
from .voxel_steps import bounding_box, components, grown, label_sizes, labelled, map_labels

PLATE_PART_MM3 = 200.0  # a plate part this large may be bone (a vessel's false plate spots are mostly smaller)
GATHER_CHUNK = 1 << 20  # voxels whose neighbours are gathered at a time (their index arrays: ~50 MB)
BONE_CONTACT_SHARE = 0.5  # CTA/MRA: a plate part is bone when this share of its surface touches bone (bone ~1, vessels ~0)
PLATE_RIM_MM = 2.0  # a component within this of a plate set aside is its rim (unless it is the largest or a vessel)


def bone_plates(plate: np.ndarray, spacing: np.ndarray, bone_of) -> np.ndarray:
    """The plate parts (connected) that are not vessels: bone-sized (at least ``PLATE_PART_MM3``) and
    bone-placed: at least ``BONE_CONTACT_SHARE`` of the part's surface voxels touch ``bone``. In a CTA, bone and
    its partial-volume band (cancellous bone in the vessels' HU window, a diploë or a skull-base core, lies between
    cortical plates); in a TOF-MRA, dark voxels or the scalp shell (marrow and fat lie inside dark cortical bone,
    or under the skin). A close-packed or bulging stretch of a vessel tree can read plate-like on the medial
    measure; it lies in tissue (or against bone on one side: a vessel in a bony groove), so it stays with its tree."""
    out = np.zeros(plate.shape, bool)
    box = bounding_box(plate, margin=1)  # a part's surface voxels' neighbours lie in it
    labels, count = labelled(plate[box], narrow_above=0)  # the reading's memory peak: 16 bits where they do
    sizes_mm3 = label_sizes(labels, count, plate[box])[1:] * float(np.prod(spacing))
    large = 1 + np.flatnonzero(sizes_mm3 >= PLATE_PART_MM3)
    if len(large) == 0:
        return out
    placed = np.zeros(count + 1, bool)
    placed[large] = contact_shares(labels, large, bone_of(box)) >= BONE_CONTACT_SHARE
    map_labels(out[box], placed, labels)
    return out


def contact_shares(labels: np.ndarray, indices, bone: np.ndarray) -> np.ndarray:
    """:func:`bone_contact` of each part in ``indices`` (labels of ``labels``)."""
    from scipy import ndimage

    bone = np.ascontiguousarray(bone)  # gathered at flat indices (:func:`bone_contact`)
    boxes = ndimage.find_objects(labels)
    return np.array([bone_contact(labels, int(index), boxes[index - 1], bone) for index in indices], float)


def bone_contact(labels: np.ndarray, index: int, box: tuple, bone: np.ndarray) -> float:
    """The share of plate part ``index``'s surface voxels (a face neighbour outside it) with a face neighbour in
    ``bone``; ``box``: the part's bounding box (slices). Where numba is loaded (:mod:`.volume_kernels`): one visit of
    the box (:func:`.medial_kernels.surface_contact`); else flat indices, ``GATHER_CHUNK`` voxels at a time, one
    gather per neighbour (the grid's border is no neighbour: a voxel there is its own)."""
    from .volume_kernels import kernels_in_use

    if kernels_in_use():
        from .medial_kernels import surface_contact

        low, high = (np.array([getattr(s, end) for s in box], np.int64) for end in ("start", "stop"))
        surface, touching = surface_contact(np.ascontiguousarray(labels), int(index), low, high,
                                            np.ascontiguousarray(bone, bool))
        return float(touching / max(surface, 1))
    every = np.flatnonzero(labels[box] == index)  # flat in the part's box (8 bytes a voxel, not 3 × 8)
    part_shape = tuple(s.stop - s.start for s in box)
    flat_labels, flat_bone = labels.reshape(-1), np.ravel(bone)
    strides = np.cumprod((1,) + labels.shape[:0:-1])[::-1]
    surface = touching = 0
    for start in range(0, len(every), GATHER_CHUNK):
        inside = np.unravel_index(every[start:start + GATHER_CHUNK], part_shape)
        position = [i + s.start for i, s in zip(inside, box)]
        flat = np.ravel_multi_index(position, labels.shape)
        on_surface = np.zeros(len(flat), bool)
        against = np.zeros(len(flat), bool)
        for axis, stride in enumerate(strides):
            for step in (-1, 1):
                within = (position[axis] > 0) if step < 0 else (position[axis] < labels.shape[axis] - 1)
                neighbour = np.where(within, flat + step * stride, flat)
                outside = flat_labels[neighbour] != index
                on_surface |= outside
                against |= outside & flat_bone[neighbour]
        surface, touching = surface + int(on_surface.sum()), touching + int(against.sum())
    return float(touching / max(surface, 1))


@dataclass(frozen=True)
class PlatesFound:
    """What :func:`plates_found` measured of a reading's mask: its ``plates`` (bool, the mask's shape; none when
    the mask is left as read), the plate share (``None``: measure the kept mask again) and, when plates are set
    aside, the mask's ``box`` and what is left of it there (``rest``: the plates and their neighbours removed)."""

    plates: np.ndarray
    share: float | None
    box: tuple[slice, ...] | None = None
    rest: np.ndarray | None = None
    rim_steps: int = 1


def plates_found(mask: np.ndarray, spacing: np.ndarray, bone_of) -> PlatesFound:
    """The bone plates of ``mask`` (:func:`bone_plates`). None when the plate share is below the
    close-call band (vessels alone) or no plate part is bone, or when nothing tube-like (< 8 voxels) would remain
    (the reading is then refused as it is). ``bone_of(box)``: what bone plates lie against, within ``box`` (CTA:
    bone and its partial-volume band beyond the kept voxels; MRA: :func:`.volume_vessels._dark_or_surface`), computed only when
    the measure finds plate parts. Worked in the mask's box (the plates, their rim and the rest lie in it)."""
    shape = medial_shape(mask, spacing, with_parts=True)
    none = np.zeros(mask.shape, bool)
    if shape.plate_share < MAX_PLATE_FRACTION - PLATE_BAND or not shape.plate.any():  # vessels: left as read
        return PlatesFound(none, shape.plate_share)
    large = bone_plates(shape.plate, spacing, bone_of)
    if not large.any():
        return PlatesFound(large, shape.plate_share)
    box = bounding_box(mask, margin=1)
    rest = mask[box] & ~grown(large[box])
    if np.count_nonzero(rest) < 8:
        return PlatesFound(none, shape.plate_share)  # nothing tube-like remains: refused
    return PlatesFound(large, None, box, rest, max(1, int(np.ceil(PLATE_RIM_MM / float(spacing.min())))))


def without_plates(mask: np.ndarray, found: PlatesFound, field_name: str, spacing: np.ndarray | None = None,
                   bone_of=None) -> tuple[np.ndarray, float | None]:
    """``mask`` without the plates ``found`` in it, its largest tube components kept, and the plate share of the
    mask returned when it is ``mask`` itself (else None: measure it again). What the plate leaves behind (its rim,
    fragments) touches it and lies in bone; so does a vessel's end (a trunk through a cancellous skull base), but a
    vessel runs on through tissue. The largest component stays; with ``bone_of(box)`` (what bone lies where
    ``mask[box]`` lies) and ``spacing``, so does a touching component of at least ``PLATE_PART_MM3`` whose medial
    axis does not run along bone (:func:`.venous_sinuses.along_bone`): a venous sinus can outweigh the arterial tree
    (:mod:`.separate_pieces` judges what stays)."""
    if found.rest is None:
        return mask, found.share
    box, large = found.box, found.plates
    parts = components(found.rest)  # no label grid where numba is loaded: the reading's peak is here
    sizes = parts.sizes()
    sizes[0] = 0  # the background
    near = grown(large[box], found.rim_steps)
    touching = 1 + np.flatnonzero(parts.touching(near)[1:])  # the parts near it
    del near  # (memory: the box's masks are the reading's peak on a whole head)
    keep = np.ones(parts.count + 1, bool)
    keep[0] = False
    others = touching[touching != int(np.argmax(sizes))]
    keep[others] = False
    if bone_of is not None:
        keep[_vessels_among(parts, others, sizes, box, spacing, bone_of)] = True
    kept = np.zeros(mask.shape, bool)
    parts.write(kept[box], keep)
    del parts  # the box's labels, where there are any, are not held through the next labelling
    return largest_components(kept, field_name=field_name), None


def _vessels_among(parts, indices: np.ndarray, sizes: np.ndarray, box: tuple[slice, ...], spacing: np.ndarray,
                   bone_of) -> list[int]:
    """The ``indices`` (components of ``parts``, in ``box`` of the mask) of at least ``PLATE_PART_MM3`` whose medial
    axis does not run along bone (:func:`.venous_sinuses.along_bone` below ``ALONG_BONE_SHARE``)."""
    from .venous_sinuses import ALONG_BONE_SHARE, along_bone_in

    out = []
    for index in indices[sizes[indices] * float(np.prod(spacing)) >= PLATE_PART_MM3]:
        chosen = np.zeros(parts.count + 1, bool)
        chosen[index] = True
        part = np.zeros(tuple(s.stop - s.start for s in box), bool)
        parts.write(part, chosen)
        near = bounding_box(part, margin=1)
        whole = tuple(slice(b.start + n.start, b.start + n.stop) for b, n in zip(box, near))
        if along_bone_in(part[near], spacing, bone_of(whole)).share < ALONG_BONE_SHARE:
            out.append(int(index))
    return out


__all__ = ["BONE_CONTACT_SHARE", "PLATE_PART_MM3", "PLATE_RIM_MM", "PlatesFound", "bone_contact", "bone_plates",
           "contact_shares", "plates_found", "without_plates"]
