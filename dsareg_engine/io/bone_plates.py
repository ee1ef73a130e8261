"""Which plate parts of a vessel reading are bone (issue 41: the diploë and the skull base of a whole-head CTA).

The medial measure (:mod:`.medial_shape`) finds the plate-shaped parts of the voxels read as vessels; a part is
set aside as bone when it is bone-sized (at least ``PLATE_PART_MM3``) and bone-placed (at least
``BONE_CONTACT_SHARE`` of its surface voxels touch what bone lies against). A vessel tree's plate-like stretches
(close-packed loops, a bulge) are smaller or lie in tissue, and stay with the tree.
"""

from __future__ import annotations

import numpy as np

from .voxel_steps import bounding_box, label_sizes

PLATE_PART_MM3 = 200.0  # a plate part this large may be bone (a vessel's false plate spots are mostly smaller)
GATHER_CHUNK = 1 << 20  # voxels whose neighbours are gathered at a time (their index arrays: ~50 MB)
BONE_CONTACT_SHARE = 0.5  # CTA/MRA: a plate part is bone when this share of its surface touches bone (bone ~1, vessels ~0)


def bone_plates(plate: np.ndarray, spacing: np.ndarray, bone_of) -> np.ndarray:
    """The plate parts (connected) that are not vessels: bone-sized (at least ``PLATE_PART_MM3``) and
    bone-placed: at least ``BONE_CONTACT_SHARE`` of the part's surface voxels touch ``bone``. In a CTA, bone and
    its partial-volume band (cancellous bone in the vessels' HU window, a diploë or a skull-base core, lies between
    cortical plates); in a TOF-MRA, dark voxels or the scalp shell (marrow and fat lie inside dark cortical bone,
    or under the skin). A close-packed or bulging stretch of a vessel tree can read plate-like on the medial
    measure; it lies in tissue (or against bone on one side: a vessel in a bony groove), so it stays with its tree."""
    from scipy import ndimage

    out = np.zeros(plate.shape, bool)
    box = bounding_box(plate, margin=1)  # a part's surface voxels' neighbours lie in it
    labels, count = ndimage.label(plate[box])
    sizes_mm3 = label_sizes(labels, count)[1:] * float(np.prod(spacing))
    large = 1 + np.flatnonzero(sizes_mm3 >= PLATE_PART_MM3)
    if len(large) == 0:
        return out
    bone = np.ascontiguousarray(bone_of(box))  # gathered at flat indices (:func:`bone_contact`)
    boxes = ndimage.find_objects(labels)
    placed = np.zeros(count + 1, bool)
    for index in large:
        placed[index] = bone_contact(labels, index, boxes[index - 1], bone) >= BONE_CONTACT_SHARE
    out[box] = placed[labels]
    return out


def bone_contact(labels: np.ndarray, index: int, box: tuple, bone: np.ndarray) -> float:
    """The share of plate part ``index``'s surface voxels (a face neighbour outside it) with a face neighbour in
    ``bone``; ``box``: the part's bounding box (slices). Flat indices, ``GATHER_CHUNK`` voxels at a time: one gather
    per neighbour (the grid's border is no neighbour: a voxel there is its own)."""
    inside = np.nonzero(labels[box] == index)
    flat_labels, flat_bone = labels.reshape(-1), np.ravel(bone)
    strides = np.cumprod((1,) + labels.shape[:0:-1])[::-1]
    surface = touching = 0
    for start in range(0, len(inside[0]), GATHER_CHUNK):
        position = [i[start:start + GATHER_CHUNK] + s.start for i, s in zip(inside, box)]
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


__all__ = ["BONE_CONTACT_SHARE", "PLATE_PART_MM3", "bone_contact", "bone_plates"]
