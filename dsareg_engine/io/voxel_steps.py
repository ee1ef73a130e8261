"""Morphology on voxel grids by shifted slices: the results of ``scipy.ndimage``'s ``binary_dilation`` (its default
cross, ``iterations``, ``mask``) and ``maximum_filter`` / ``minimum_filter`` (a cube, ``mode="reflect"``), each a
few whole-array operations per axis instead of a loop over every voxel's neighbourhood; and a mask's bounding box
from its projections on the axes (not from the index list of its voxels).

On a whole-head CTA's boxes (30–50 M voxels, issue 41) one step of ``binary_dilation`` took ~0.25 s per 16 M voxels
where six shifted ORs take ~0.015 s; a cube's maximum is separable (one axis after the other) and, in ``reflect``
mode, the maximum over the window clipped to the grid (a reflected index lies inside the window).
"""

from __future__ import annotations

import numpy as np

LABEL_SLAB = 1 << 22  # voxels counted at a time by :func:`label_sizes` (32 MB of 64-bit labels)


def bounding_box(mask: np.ndarray, margin: int = 0) -> tuple[slice, ...] | None:
    """The slices of ``mask``'s bounding box grown by ``margin`` voxels (clipped to the grid); None if empty.
    Found from the projections of the mask on each axis (no index list of its voxels)."""
    hits = [np.flatnonzero(mask.any(axis=tuple(b for b in range(mask.ndim) if b != a))) for a in range(mask.ndim)]
    if any(len(h) == 0 for h in hits):
        return None
    return tuple(slice(max(int(h[0]) - margin, 0), min(int(h[-1]) + margin + 1, size))
                 for h, size in zip(hits, mask.shape))


def label_sizes(labels: np.ndarray, count: int) -> np.ndarray:
    """Voxels per label ``0..count`` of an integer ``labels`` grid (``ndimage.label``'s), counted slab by slab: a
    whole-grid ``np.bincount`` holds a 64-bit copy of the grid (a skull's box: 400 MB)."""
    sizes = np.zeros(count + 1, np.int64)
    flat = labels.reshape(-1)
    for start in range(0, flat.size, LABEL_SLAB):
        sizes += np.bincount(flat[start:start + LABEL_SLAB], minlength=count + 1)
    return sizes


def grown(mask: np.ndarray, steps: int = 1, within: np.ndarray | None = None) -> np.ndarray:
    """bool: ``mask`` grown ``steps`` times by its face neighbours (``binary_dilation(mask, iterations=steps,
    mask=within)``): with ``within``, a step adds only voxels of ``within``; the grid's outside is empty."""
    out = np.array(mask, bool)
    for _ in range(steps):
        step = _face_neighbours(out)  # out and its neighbours
        if within is not None:
            step &= within
            step |= out
        out = step
    return out


def _face_neighbours(mask: np.ndarray) -> np.ndarray:
    """``mask`` or a face neighbour in it (one step of the cross), the outside empty."""
    out = mask.copy()
    for axis in range(mask.ndim):
        ahead = [slice(None)] * mask.ndim
        behind = [slice(None)] * mask.ndim
        ahead[axis], behind[axis] = slice(1, None), slice(None, -1)
        out[tuple(ahead)] |= mask[tuple(behind)]
        out[tuple(behind)] |= mask[tuple(ahead)]
    return out


def cube_maximum(values: np.ndarray, size: int) -> np.ndarray:
    """``maximum_filter(values, size=size)`` (``size`` odd, ``mode="reflect"``): the maximum over the cube of
    ``size`` voxels a side centred on each voxel, clipped to the grid; one axis after the other."""
    return _cube_extreme(values, size, np.maximum)


def cube_minimum(values: np.ndarray, size: int) -> np.ndarray:
    """``minimum_filter(values, size=size)`` (``size`` odd, ``mode="reflect"``), as :func:`cube_maximum`."""
    return _cube_extreme(values, size, np.minimum)


def _cube_extreme(values: np.ndarray, size: int, extreme) -> np.ndarray:
    if size % 2 != 1:
        raise ValueError(f"an odd cube side is needed, got {size}")
    out = np.array(values)
    for axis in range(values.ndim):
        source = out.copy() if size > 1 else out
        for shift in range(1, size // 2 + 1):
            if shift >= out.shape[axis]:
                break
            ahead = [slice(None)] * out.ndim
            behind = [slice(None)] * out.ndim
            ahead[axis], behind[axis] = slice(shift, None), slice(None, -shift)
            extreme(out[tuple(ahead)], source[tuple(behind)], out=out[tuple(ahead)])
            extreme(out[tuple(behind)], source[tuple(ahead)], out=out[tuple(behind)])
    return out


__all__ = ["bounding_box", "cube_maximum", "cube_minimum", "grown", "label_sizes"]
