"""Numba twins of two whole-box steps of :mod:`.voxel_steps` (cached on disk), used where numba is loaded
(:mod:`.volume_kernels`): one face-neighbour step of a mask (:func:`face_step`: ``binary_dilation``'s cross, the
outside empty) and a label table mapped onto a box (:func:`mapped`: ``out[...] = table[labels]``). Each gives the
same voxels as the numpy steps in one pass over the box (the numpy step: a copy and six shifted ORs; a fancy-index
gather and its temporary), where a whole-head reading's boxes (~40 M voxels) make them memory-bound.
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True)
def face_step(mask, out):
    """``out`` (bool, ``mask``'s shape) set to ``mask`` or a face neighbour in it; the grid's outside is empty."""
    n0, n1, n2 = mask.shape
    for i in range(n0):
        for j in range(n1):
            for k in range(n2):
                out[i, j, k] = (mask[i, j, k]
                                or (i > 0 and mask[i - 1, j, k]) or (i < n0 - 1 and mask[i + 1, j, k])
                                or (j > 0 and mask[i, j - 1, k]) or (j < n1 - 1 and mask[i, j + 1, k])
                                or (k > 0 and mask[i, j, k - 1]) or (k < n2 - 1 and mask[i, j, k + 1]))


@njit(cache=True)
def mapped(out, table, labels):
    """``out[...] = table[labels]`` over a 3D box (``out`` any layout: a box of a larger grid)."""
    n0, n1, n2 = labels.shape
    for i in range(n0):
        for j in range(n1):
            for k in range(n2):
                out[i, j, k] = table[labels[i, j, k]]


VOXEL_KERNELS = (face_step, mapped)
"""The dispatchers of this module (the warm-up's ``volumes`` group)."""


def compile_voxel_kernels() -> None:
    """Both kernels compiled (or loaded from numba's cache) with the types the readings pass: C-ordered bool masks;
    bool tables mapped through 16- and 32-bit labels onto a whole grid or a box of one."""
    cube = np.ones((2, 2, 3), bool)
    face_step(cube, np.empty_like(cube))
    table = np.ones(2, bool)
    for labels in (np.uint16, np.int32):
        mapped(np.empty((2, 2, 3), bool), table, np.ones((2, 2, 3), labels))
        mapped(np.empty((2, 2, 4), bool)[:, :, 1:], table, np.ones((2, 2, 3), labels))


__all__ = ["VOXEL_KERNELS", "compile_voxel_kernels", "face_step", "mapped"]
