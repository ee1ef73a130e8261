"""Numba twins of two whole-box steps of :mod:`.voxel_steps` (cached on disk), used where numba is loaded
(:mod:`.volume_kernels`): one face-neighbour step of a mask (:func:`face_step`: ``binary_dilation``'s cross, the
outside empty), a label table mapped onto a box (:func:`mapped`: ``out[...] = table[labels]``) and a CTA's
plateau test at chosen voxels (:func:`flat_at`: its gradient's length below a limit). Each gives the same voxels as
the numpy steps in one pass (the numpy steps: a copy and six shifted ORs; a fancy-index gather and its temporary;
six gathers and a C-ordered copy of the grid), where a whole-head reading's boxes (~40 M voxels) make them
memory-bound.
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


@njit(cache=True)
def flat_at(values, index, spacing, limit):
    """For each flat ``index`` (C order) of the float32 grid ``values`` (3D, any layout): whether its gradient's
    length is below ``limit`` (float32): per axis the difference of the neighbours ahead and behind (the voxel
    itself at the grid's ends) over twice the spacing, formed as numpy forms it in
    :func:`.volume_vessels._plateau` (the float32 difference, divided and squared in float64, summed into a
    float32; the root in float32)."""
    n0, n1, n2 = values.shape
    out = np.empty(len(index), np.bool_)
    for n in range(len(index)):
        flat = index[n]
        i, rest = flat // (n1 * n2), flat % (n1 * n2)
        j, k = rest // n2, rest % n2
        here = values[i, j, k]
        squared = np.float32(0.0)
        ahead, behind = (values[i + 1, j, k] if i < n0 - 1 else here), (values[i - 1, j, k] if i > 0 else here)
        step = np.float64(ahead - behind) / (2.0 * spacing[0])
        squared = np.float32(np.float64(squared) + step * step)
        ahead, behind = (values[i, j + 1, k] if j < n1 - 1 else here), (values[i, j - 1, k] if j > 0 else here)
        step = np.float64(ahead - behind) / (2.0 * spacing[1])
        squared = np.float32(np.float64(squared) + step * step)
        ahead, behind = (values[i, j, k + 1] if k < n2 - 1 else here), (values[i, j, k - 1] if k > 0 else here)
        step = np.float64(ahead - behind) / (2.0 * spacing[2])
        squared = np.float32(np.float64(squared) + step * step)
        out[n] = np.sqrt(squared) < limit
    return out


VOXEL_KERNELS = (face_step, mapped, flat_at)
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
    for order in "CF":  # a smoothed box: either order (:mod:`.smoothing_kernels`)
        flat_at(np.zeros((2, 2, 3), np.float32, order=order), np.arange(3), np.ones(3), np.float32(1.0))


__all__ = ["VOXEL_KERNELS", "compile_voxel_kernels", "face_step", "flat_at", "mapped"]
