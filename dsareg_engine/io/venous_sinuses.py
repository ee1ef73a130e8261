"""Dural venous sinuses read as vessels (issue 41: a CTA with venous filling).

A CTA taken late, or a slow circulation, fills the dural venous sinuses (superior sagittal, transverse, sigmoid,
on to the jugular veins). They are tubes in the vessels' window, so the reading keeps them, and a venous system
outweighs a carotid territory several times; a DSA run's arterial phase holds none of it, so the registration would
fit the wrong structure.

The sinuses lie in the dura, their lumen against the skull's inner table along their whole course. Arteries lie in
the subarachnoid space and touch bone in their canals only (the petrous carotid, the vertebral foramina). The
measure (:func:`along_bone`): the share of a separate piece's medial axis (:mod:`.medial_shape`) whose lumen
touches bone, each medial point weighted by its cross-section (radius²): a point touches when a surface voxel of
the piece against bone lies within its radius plus ``TOUCH_MM``. A piece at or above ``ALONG_BONE_SHARE`` whose
mean radius is at least ``SINUS_RADIUS_MM`` is a sinus; :mod:`.separate_pieces` sets it aside.

Measured on whole heads from a generator written apart from ours: sinuses 0.97–1.00; vessel trees 0.09–0.17.
Not handled: a venous system joined to the arteries at the voxel scale (a filled cavernous sinus around the carotid,
a cortical vein beside an artery) is one piece with them, and stays.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .medial_shape import MAX_WORK_VOXELS, medial_points, to_working_grid, working_mm
from .voxel_steps import grown

ALONG_BONE_SHARE = 0.7  # sinuses ~1 (against the inner table), vessel trees ~0.1-0.2 (their canals)
ALONG_BONE_BAND = 0.15  # a piece this close to the share: a close call
TOUCH_MM = 1.0  # a medial point's lumen touches bone when a surface voxel against bone lies within its radius + this
SINUS_RADIUS_MM = 1.5  # a sinus's lumen is 5-10 mm across; a thinner piece (a vessel, a noise net) is no sinus
PIECE_WORK_VOXELS = MAX_WORK_VOXELS // 4  # a piece's working grid at most (a venous system spans the head: ~0.8 mm)


@dataclass(frozen=True)
class AlongBone:
    """:func:`along_bone` of a piece: the ``share`` (0–1) of its medial axis whose lumen touches bone and its mean
    radius (``radius_mm``), both weighted by cross-section (radius²)."""

    share: float
    radius_mm: float

    @property
    def sinus(self) -> bool:
        """A sinus by both: along bone and thick enough."""
        return self.share >= ALONG_BONE_SHARE and self.radius_mm >= SINUS_RADIUS_MM


def along_bone(piece: np.ndarray, spacing: np.ndarray, touching: np.ndarray) -> AlongBone:
    """How far ``piece``'s medial axis (:mod:`.medial_shape`) runs with its lumen against bone: a medial point
    touches when a voxel of ``touching`` lies within its radius plus ``TOUCH_MM``.

    Args:
        piece: bool (Z, Y, X), the piece in its box; ``spacing``: the voxel (mm) per axis.
        touching: bool, the same shape: the piece's voxels with a face neighbour in bone.
    """
    from scipy.spatial import cKDTree

    box_mm3 = float(np.prod(np.asarray(piece.shape) * spacing))
    work_mm = max(working_mm(piece.shape, spacing), (box_mm3 / PIECE_WORK_VOXELS) ** (1.0 / 3.0))
    work, zoom = to_working_grid(piece, spacing, work_mm)
    points, radius_vox = medial_points(work, work_mm)
    if len(points) == 0:  # no ridge (a box-shaped block): its deepest voxel stands for it
        points, radius_vox = _deepest(work)
        if len(points) == 0:
            return AlongBone(0.0, 0.0)
    weight = np.maximum(radius_vox, 1.0) ** 2
    radius_mm = float((weight * radius_vox).sum() / weight.sum()) * work_mm
    if not touching.any():
        return AlongBone(0.0, radius_mm)
    at_mm = ((points + 0.5) / zoom - 0.5) * spacing  # the working grid's voxel centres (ndimage.zoom's grid_mode)
    distance_mm = cKDTree(np.argwhere(touching) * spacing).query(at_mm)[0]
    along = distance_mm <= radius_vox * work_mm + TOUCH_MM
    return AlongBone(float((weight * along).sum() / weight.sum()), radius_mm)


def _deepest(work: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The deepest voxel of ``work`` (``(1, 3)``, or none when empty) and its depth (working voxels)."""
    from scipy import ndimage

    if not work.any():
        return np.zeros((0, 3), int), np.zeros(0)
    depth = ndimage.distance_transform_edt(np.pad(work, 1))[1:-1, 1:-1, 1:-1]
    at = np.unravel_index(int(np.argmax(depth)), work.shape)
    return np.array([at]), np.array([float(depth[at]) - 0.25])


def along_bone_in(piece: np.ndarray, spacing: np.ndarray, bone: np.ndarray) -> AlongBone:
    """:func:`along_bone` of ``piece`` (bool, its box grown by a voxel: its surface voxels' neighbours) beside
    ``bone`` (bool, the same box)."""
    return along_bone(piece, np.asarray(spacing, float), piece & grown(bone))


def along_bone_of(labels: np.ndarray, indices, bone: np.ndarray, spacing: np.ndarray) -> list[AlongBone]:
    """:func:`along_bone` of each piece in ``indices`` (labels of ``labels``), each in its box grown by a voxel
    (its surface voxels' neighbours); ``bone``: bool, ``labels``' shape."""
    from scipy import ndimage

    boxes = ndimage.find_objects(labels)
    out = []
    for index in indices:
        near = tuple(slice(max(s.start - 1, 0), min(s.stop + 1, n)) for s, n in zip(boxes[index - 1], labels.shape))
        out.append(along_bone_in(labels[near] == index, spacing, bone[near]))
    return out


__all__ = ["ALONG_BONE_BAND", "ALONG_BONE_SHARE", "SINUS_RADIUS_MM", "TOUCH_MM", "AlongBone", "along_bone",
           "along_bone_in", "along_bone_of"]
