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
LABEL16_VOXELS = 80_000_000  # grids this large are labelled in 16 bits where they can be (:func:`labelled`)
MAP_CHUNK = 1 << 23  # voxels mapped through a label table at a time by :func:`map_labels`


def bounding_box(mask: np.ndarray, margin: int = 0) -> tuple[slice, ...] | None:
    """The slices of ``mask``'s bounding box grown by ``margin`` voxels (clipped to the grid); None if empty.
    Found from the projections of the mask on each axis (no index list of its voxels)."""
    hits = [np.flatnonzero(mask.any(axis=tuple(b for b in range(mask.ndim) if b != a))) for a in range(mask.ndim)]
    if any(len(h) == 0 for h in hits):
        return None
    return tuple(slice(max(int(h[0]) - margin, 0), min(int(h[-1]) + margin + 1, size))
                 for h, size in zip(hits, mask.shape))


def labelled(mask: np.ndarray, *, narrow_above: int | None = None) -> tuple[np.ndarray, int]:
    """``ndimage.label(mask)`` (face neighbours); on a grid of more than ``narrow_above`` (``LABEL16_VOXELS``) voxels
    in 16-bit labels where the components fit (up to 65,535), else 32-bit. 16 bits take 2 bytes a voxel, not 4
    (0.25 GB less on a 600-slice head's box), and ~30 % more time (scipy labels a narrower type more slowly): on
    smaller grids time wins, unless the caller labels at its reading's memory peak (:func:`.bone_plates.bone_plates`).
    A 3D mask where numba is loaded (:mod:`.volume_kernels`): by its runs (:func:`.label_kernels.runs_labelled`, the
    same labels), unless it has too many."""
    from .volume_kernels import kernels_in_use

    narrow = mask.size > (LABEL16_VOXELS if narrow_above is None else narrow_above)
    if mask.ndim == 3 and kernels_in_use():
        from .label_kernels import runs_labelled

        found = runs_labelled(mask, narrow)
        if found is not None:
            return found
    return _scipy_labelled(mask, narrow)


def _scipy_labelled(mask: np.ndarray, narrow: bool) -> tuple[np.ndarray, int]:
    from scipy import ndimage

    if narrow:
        try:
            return ndimage.label(mask, output=np.uint16)
        except RuntimeError:  # scipy: "insufficient bit-depth in requested output type"
            pass
    return ndimage.label(mask)


class LabelledComponents:
    """A mask's components as a label grid (:func:`labelled`), asked what :class:`.label_kernels.ComponentRuns`
    is asked: ``count``, ``sizes()``, ``touching(near)``, ``write(out, chosen)``."""

    def __init__(self, mask: np.ndarray, labels: np.ndarray, count: int):
        self.mask, self.labels, self.count = mask, labels, int(count)

    def sizes(self) -> np.ndarray:
        """Voxels per component ``0 … count`` (int64; 0: the background)."""
        return label_sizes(self.labels, self.count, self.mask)

    def touching(self, near: np.ndarray) -> np.ndarray:
        """bool per component ``0 … count``: whether one of its voxels is in ``near``."""
        return np.bincount(self.labels[near], minlength=self.count + 1) > 0

    def write(self, out: np.ndarray, chosen: np.ndarray) -> None:
        """``out[...] = chosen[labels]`` (:func:`map_labels`; ``chosen[0]``, the background's, False)."""
        map_labels(out, chosen, self.labels)


def components(mask: np.ndarray):
    """A bool ``mask``'s components (face neighbours, ``ndimage.label``'s numbering) to be sized, tested for contact
    and written back: from its runs with no label grid (:func:`.label_kernels.component_runs`; a 600-slice head's box
    labelled in 16 bits is 0.26 GB) where this process uses the volume kernels and the mask has few enough runs,
    else from :func:`labelled`'s grid (:class:`LabelledComponents`)."""
    from .volume_kernels import kernels_in_use

    narrow = mask.size > LABEL16_VOXELS
    if mask.ndim == 3 and kernels_in_use():
        from .label_kernels import component_runs

        found = component_runs(mask)
        if found is not None:
            return found
    return LabelledComponents(mask, *_scipy_labelled(mask, narrow))


def map_labels(out: np.ndarray, table: np.ndarray, labels: np.ndarray) -> None:
    """``out[...] = table[labels]`` a slab of ``MAP_CHUNK`` voxels at a time (no temporary of ``labels``' size):
    ``out`` a view of ``labels``' shape (a box of a larger grid); in one pass where numba is loaded
    (:func:`.voxel_kernels.mapped`)."""
    from .volume_kernels import kernels_in_use

    if labels.ndim == 3 and kernels_in_use():
        from .voxel_kernels import mapped

        mapped(out, table, labels)
        return
    step = max(1, MAP_CHUNK // max(labels[0].size, 1))
    for start in range(0, len(labels), step):
        out[start:start + step] = table[labels[start:start + step]]


def label_sizes(labels: np.ndarray, count: int, inside: np.ndarray | None = None) -> np.ndarray:
    """Voxels per label ``0..count`` of an integer ``labels`` grid (``ndimage.label``'s). With ``inside`` (the mask
    that was labelled), counted over its voxels only (a whole head's box is mostly background: ~4 x faster); else
    slab by slab: a whole-grid ``np.bincount`` holds a 64-bit copy of the grid (a skull's box: 400 MB)."""
    sizes = np.zeros(count + 1, np.int64)
    step = max(1, LABEL_SLAB // max(labels[0].size, 1))  # a slab of planes at a time
    for start in range(0, len(labels), step):
        slab = labels[start:start + step]
        sizes += np.bincount((slab if inside is None else slab[inside[start:start + step]]).reshape(-1),
                             minlength=count + 1)
    if inside is not None:
        sizes[0] = inside.size - int(sizes[1:].sum())
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
    """``mask`` or a face neighbour in it (one step of the cross), the outside empty: one pass of
    :func:`.voxel_kernels.face_step` over a 3D mask where numba is loaded, else a copy and six shifted ORs."""
    from .volume_kernels import kernels_in_use

    if mask.ndim == 3 and kernels_in_use():
        from .voxel_kernels import face_step

        out = np.empty(mask.shape, bool)
        face_step(np.ascontiguousarray(mask, bool), out)
        return out
    out = mask.copy()
    for axis in range(mask.ndim):
        ahead = [slice(None)] * mask.ndim
        behind = [slice(None)] * mask.ndim
        ahead[axis], behind[axis] = slice(1, None), slice(None, -1)
        out[tuple(ahead)] |= mask[tuple(behind)]
        out[tuple(behind)] |= mask[tuple(ahead)]
    return out


def filled_holes(mask: np.ndarray) -> np.ndarray:
    """``ndimage.binary_fill_holes(mask)`` (its default structure: face neighbours, 2D or 3D): ``mask`` and the
    background voxels that no path of face-neighbouring background voxels joins to the grid's border. One labelling
    of the background, not a dilation repeated until nothing changes (a 160-slice TOF's head mask, filled in 3D and
    slice by slice: 2.9 → 1.6 CPU s)."""
    background = ~np.asarray(mask, bool)
    labels, count = labelled(background, narrow_above=0)  # 16 bits where they fit: a head's grid is labelled whole
    if count == 0:
        return ~background
    outside = np.zeros(count + 1, bool)
    for axis in range(labels.ndim):  # the components with a voxel on a face of the grid
        outside[np.unique(labels.take(0, axis))] = True
        outside[np.unique(labels.take(-1, axis))] = True
    outside[0] = False
    return ~outside[labels]


def cube_maximum(values: np.ndarray, size: int) -> np.ndarray:
    """``maximum_filter(values, size=size)`` (``size`` odd, ``mode="reflect"``): the maximum over the cube of
    ``size`` voxels a side centred on each voxel, clipped to the grid; one axis after the other."""
    return _cube_extreme(values, size, np.maximum)


def cube_minimum(values: np.ndarray, size: int, *, in_place: bool = False) -> np.ndarray:
    """``minimum_filter(values, size=size)`` (``size`` odd, ``mode="reflect"``), as :func:`cube_maximum`;
    ``in_place``: written into ``values`` (a caller's temporary: one grid fewer at a reading's memory peak)."""
    return _cube_extreme(values, size, np.minimum, in_place)


def _cube_extreme(values: np.ndarray, size: int, extreme, in_place: bool = False) -> np.ndarray:
    if size % 2 != 1:
        raise ValueError(f"an odd cube side is needed, got {size}")
    out = values if in_place else np.array(values)
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
        del source  # (memory: one copy of the grid at a time, not two while the next is made)
    return out


__all__ = ["LabelledComponents", "bounding_box", "components", "cube_maximum", "cube_minimum", "filled_holes", "grown",
           "label_sizes", "labelled", "map_labels"]
