"""Tube or plate, measured on the medial axis in millimetres (independent of the voxel size).

Vessels are tubes: around a point of their medial axis at depth ``r`` (the radius), a ball of radius
``R = BALL_PER_RADIUS × r`` holds about ``π r² × 2R`` of the structure (a length 2R of the tube). Bone read as
vessel (a skull's diploë between its tables, a skull-base slab, a closed shell) is a plate: the same ball holds
``π R² × 2r``, ``BALL_PER_RADIUS`` times more. The *fill ratio* (volume in the ball ÷ ``π r² 2R``) is about 1 on
a tube (0.5–1.8 with ends, junctions and bulges), about ``BALL_PER_RADIUS`` (4) on a plate (2.2–4 with its
edges), at any voxel size. The measure:

1. the mask is resampled to an isotropic working grid of ``WORK_MM`` (trilinear; anisotropic voxels read per
   axis), so what follows sees the same shape at any voxel size; a box that would exceed ``MAX_WORK_VOXELS`` there
   (a skull's diploë across a whole head, a coarse-voxel volume upsampled) is worked on a coarser grid holding that
   many: time and memory follow a bound, not the box's size in mm;
2. the depth (distance to the outside, mm) is computed; medial points are its ridge (slope below
   ``MEDIAL_SLOPE``, 1 elsewhere) near its local top (within 0.75 voxel of the deepest within 2 voxels),
   and every voxel of a structure two voxels across; ``r`` is that local top less a quarter voxel;
3. a medial point is a plate point when its fill ratio exceeds ``PLATE_RATIO``.

:func:`medial_shape` gives the plate share of the medial points and, on request, which voxels of the mask
belong to plate parts (nearer a plate medial point than a tube one), on the mask's own grid.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from .voxel_steps import bounding_box, cube_maximum, grown

WORK_MM = 0.5
BALL_PER_RADIUS = 4.0
MIN_BALL_MM = 3.0
PLATE_RATIO = 1.7
MEDIAL_SLOPE = 0.8  # |∇ depth| (mm per mm) below which a voxel is on the ridge of the depth
MAX_SAMPLES = 4000  # medial points whose fill ratio is measured (the others take their nearest one's)
MAX_WORK_VOXELS = 16_000_000  # the working grid's voxels at most (~1 GB at the peak of the measure)
SHELL_R2 = 16  # depths up to √SHELL_R2 voxels are found shell by shell (the deeper ones are queries)
KERNEL_SHELL_R2 = 64  # the same with numba (:func:`.medial_kernels.shell_depths`): one voxel's offsets at a time
BACK_CHUNK = 1 << 22  # mask voxels whose plate value is interpolated at a time
SURE_STEPS = 2  # voxels per axis: a voxel this near a plate medial point and far from tube ones is plate


@dataclass(frozen=True)
class MedialShape:
    """The medial measure of a mask.

    Attributes:
        plate_share: plate medial points ÷ medial points, each weighted by its radius² (the volume it stands
            for: a thin vessel is all medial points), 0 = all tube, 1 = all sheet.
        medial_points: medial points on the working grid.
        plate: bool, the mask's shape: voxels of plate parts (None unless asked for).
    """

    plate_share: float
    medial_points: int
    plate: np.ndarray | None = None


def working_mm(shape, spacing_mm) -> float:
    """The working grid's voxel (mm) for a box of ``shape`` voxels of ``spacing_mm``: ``WORK_MM``, or coarser so that
    the grid holds at most ``MAX_WORK_VOXELS``."""
    voxels = float(np.prod(np.asarray(shape, float) * np.asarray(spacing_mm, float) / WORK_MM))
    return WORK_MM if voxels <= MAX_WORK_VOXELS else WORK_MM * (voxels / MAX_WORK_VOXELS) ** (1.0 / 3.0)


def to_working_grid(mask: np.ndarray, spacing_mm, work_mm: float = WORK_MM) -> tuple[np.ndarray, np.ndarray]:
    """``mask`` (bool) resampled to ``work_mm`` voxels (trilinear, ≥ 0.5 inside); and the zoom per axis.

    ``ndimage.zoom``'s grid (``grid_mode``, ``nearest`` at the borders) interpolated at the working voxels whose
    eight neighbours on the mask's grid hold a mask voxel (the others are 0), with its coordinates and weights
    (``map_coordinates``): the same voxels, without a float copy of the mask's whole box (a skull's: 50 M voxels)."""
    from scipy import ndimage

    zoom = np.asarray(spacing_mm, float) / work_mm
    if np.allclose(zoom, 1.0):
        return mask.astype(bool), zoom
    shape = np.round(np.asarray(mask.shape) * zoom).astype(int)
    if (shape == 0).any():
        return np.zeros(shape, bool), zoom
    near, coordinates = np.asarray(mask, bool), []
    for axis, (size, zoomed) in enumerate(zip(mask.shape, shape)):
        at = (np.arange(zoomed) + 0.5) * (size / zoomed) - 0.5  # ndimage.zoom's coordinate (grid_mode)
        below = np.floor(at).astype(np.intp)
        near = np.take(near, np.clip(below, 0, size - 1), axis) | np.take(near, np.clip(below + 1, 0, size - 1), axis)
        coordinates.append(at)
    index = np.nonzero(near)
    values = ndimage.map_coordinates(np.asarray(mask, bool).view(np.uint8), [at[i] for at, i in zip(coordinates, index)],
                                     order=1, mode="nearest", output=np.float32)
    work = np.zeros(near.shape, bool)
    work[index] = values >= 0.5
    return work, zoom


def medial_ratio(work: np.ndarray, work_mm: float = WORK_MM) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Medial points ``(N, 3)`` (working-grid indices) of the mask ``work`` (voxels of ``work_mm``), their volume
    scaling exponent ``(N,)`` and their radius ``(N,)`` in working voxels."""
    from scipy.spatial import cKDTree

    points, radius_vox = medial_points(work, work_mm)
    if len(points) == 0:
        return points, np.zeros(0), np.zeros(0)
    sample = np.arange(len(points))
    if len(points) > MAX_SAMPLES:
        sample = np.sort(np.random.default_rng(0).choice(len(points), MAX_SAMPLES, replace=False))
    ball_vox = np.maximum(BALL_PER_RADIUS * radius_vox[sample], MIN_BALL_MM / work_mm)
    inside, half = _ball_counts(work, points[sample], ball_vox)
    ratio = np.log2(inside / np.maximum(half, 1))
    if len(sample) < len(points):  # the others take their nearest measured neighbour's
        ratio = ratio[cKDTree(points[sample]).query(points)[1]]
    return points, ratio, radius_vox


def _ball_counts(work: np.ndarray, centres: np.ndarray, ball_vox: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The voxels of ``work`` within ``ball_vox`` and within half of it (distance ≤ radius) of each of ``centres``:
    :func:`.medial_kernels.ball_counts` where numba is loaded (:mod:`.volume_kernels`; rows under 65,535 voxels),
    else ``cKDTree.query_ball_point`` (the same counts)."""
    from scipy.spatial import cKDTree

    from .volume_kernels import kernels_in_use

    if work.shape[2] < np.iinfo(np.uint16).max and kernels_in_use():
        from .medial_kernels import ball_counts

        return ball_counts(np.ascontiguousarray(work, bool), np.ascontiguousarray(centres, np.int64),
                           np.asarray(ball_vox, np.float64), np.asarray(ball_vox, np.float64) / 2.0)
    voxels = cKDTree(np.argwhere(work), balanced_tree=False, compact_nodes=False)  # counts: any tree's, built 3x faster
    return (voxels.query_ball_point(centres, ball_vox, return_length=True),
            voxels.query_ball_point(centres, ball_vox / 2.0, return_length=True))


def medial_points(work: np.ndarray, work_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """The medial points ``(N, 3)`` of ``work`` and their radius (working voxels): the voxels of ``work`` as deep as
    the deepest within 2 voxels less 0.75 voxel, on the ridge of the depth (``|∇ depth|`` below ``MEDIAL_SLOPE``,
    central differences as ``np.gradient``) or in a structure two voxels across. The depth's local tops are
    filtered on its squared voxel lengths (integers: the same order as the millimetres), at the inside voxels only
    (:func:`.medial_kernels.maxima_at`: ``maximum_filter``'s values there); the slope is formed at the voxels near a
    top only, with ``np.gradient``'s operations (the same points as over the whole grid)."""

    squared = _depth_squared(work)
    index = np.flatnonzero(work)
    within_two, within_one = _local_maxima(squared, index)
    top = np.sqrt(within_two.astype(np.float64)) * work_mm
    depth = np.sqrt(squared.ravel()[index].astype(np.float64)) * work_mm
    near_top = depth >= top - 0.75 * work_mm
    index, top = index[near_top], top[near_top]
    thin = within_one[near_top] <= 1  # two voxels across: all medial
    medial = thin.copy()
    slope = _slope_at(squared, index[~thin], work_mm)
    medial[~thin] = slope < MEDIAL_SLOPE
    points = np.stack(np.unravel_index(index[medial], work.shape), axis=1)
    return points, top[medial] / work_mm - 0.25


def _local_maxima(squared: np.ndarray, index: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The maxima of ``squared`` over the 5³ and the 3³ cube around each flat ``index`` (``maximum_filter``'s values
    there): :func:`.medial_kernels.maxima_at` where this process has numba loaded
    (:mod:`.volume_kernels`), else two whole-grid filters."""
    from .volume_kernels import kernels_in_use

    if not kernels_in_use():
        return cube_maximum(squared, 5).ravel()[index], cube_maximum(squared, 3).ravel()[index]
    from .medial_kernels import maxima_at

    return maxima_at(squared, index, 2, 1)


def _slope_at(squared: np.ndarray, index: np.ndarray, work_mm: float) -> np.ndarray:
    """``|∇ depth|`` (mm per mm) at the flat ``index`` of the grid whose depths are ``√squared × work_mm``: per axis
    ``np.gradient``'s central difference ``(f[i+1] − f[i−1]) / (2 h)``, one-sided ``(f[1] − f[0]) / h`` at the ends;
    the squares summed axis by axis, then the root."""
    position = np.unravel_index(index, squared.shape)
    flat = squared.ravel()
    slope = np.zeros(len(index))
    for axis, stride in enumerate(np.array(squared.strides) // squared.itemsize):
        at, size = position[axis], squared.shape[axis]
        up = np.where(at < size - 1, index + stride, index)
        down = np.where(at > 0, index - stride, index)
        step = np.where((at > 0) & (at < size - 1), 2.0 * work_mm, work_mm)
        difference = np.sqrt(flat[up].astype(np.float64)) * work_mm - np.sqrt(flat[down].astype(np.float64)) * work_mm
        slope += (difference / step) ** 2
    return np.sqrt(slope)


def medial_shape(mask: np.ndarray, spacing_mm, *, with_parts: bool = False) -> MedialShape:
    """The plate share of ``mask`` (bool, voxel ``spacing_mm`` per axis) and optionally its plate voxels."""
    if not mask.any():
        return MedialShape(0.0, 0, np.zeros(mask.shape, bool) if with_parts else None)
    low, high = _box(mask, margin=1)
    work_mm = working_mm(high - low, spacing_mm)
    work, zoom = to_working_grid(mask[low[0]:high[0], low[1]:high[1], low[2]:high[2]], spacing_mm, work_mm)
    points, ratio, radius_vox = medial_ratio(work, work_mm)
    if len(points) == 0:
        return MedialShape(0.0, 0, np.zeros(mask.shape, bool) if with_parts else None)
    is_plate = ratio > PLATE_RATIO
    weight = np.maximum(radius_vox, 1.0) ** 2  # a medial point stands for its cross-section's volume
    share = float((weight * is_plate).sum() / weight.sum())
    if not with_parts:
        return MedialShape(share, len(points))
    plate = np.zeros(mask.shape, bool)
    if is_plate.any():
        region = tuple(slice(a, b) for a, b in zip(low, high))
        plate[region] = _back_on_mask(_nearer_plate(work, points, is_plate), zoom, mask[region])
    return MedialShape(share, len(points), plate)


def _back_on_mask(work_plate: np.ndarray, zoom: np.ndarray, part: np.ndarray) -> np.ndarray:
    """The working grid's plate voxels back on the mask ``part`` (its box): ``work_plate`` zoomed back by ``1 / zoom``
    (trilinear, ``grid_mode``, ``nearest`` at the borders, as ``ndimage.zoom``), its last plane repeated where the
    zoomed grid is short, ≥ 0.5 and in ``part``. Interpolated at ``part``'s voxels only (a whole-head box holds ~10 ×
    as many): the same coordinates and weights as ``ndimage.zoom``'s, the same voxels. Where numba is loaded
    (:mod:`.volume_kernels`), a voxel whose eight corners on the working grid agree takes their value
    (:func:`.medial_kernels.corner_agreement`; the weights sum to 1): only the others are interpolated."""
    from scipy import ndimage

    from .volume_kernels import kernels_in_use

    every = np.flatnonzero(part)
    zoomed = np.round(np.asarray(work_plate.shape) / np.asarray(zoom, float)).astype(int)
    plate, out = np.ascontiguousarray(work_plate, bool).view(np.uint8), np.zeros(part.shape, bool)  # (no float copy)
    tables = [(np.minimum(np.arange(size), zoomed[axis] - 1) + 0.5) * (work_plate.shape[axis] / zoomed[axis]) - 0.5
              for axis, size in enumerate(part.shape)]  # ``ndimage.zoom``'s coordinate of each index, per axis
    if kernels_in_use():
        from .medial_kernels import corner_agreement

        corners = [np.clip(np.floor(table), 0, n - 1).astype(np.int64) for table, n in zip(tables, plate.shape)]
        agreed = corner_agreement(plate, every, np.array(part.shape, np.int64), *corners)
        out.ravel()[every[agreed == 1]] = True
        every = every[agreed < 0]
    for start in range(0, len(every), BACK_CHUNK):  # a chunk at a time: its coordinates (24 bytes a voxel) stay small
        inside = np.unravel_index(every[start:start + BACK_CHUNK], part.shape)
        coordinates = [table[index] for table, index in zip(tables, inside)]
        out[inside] = ndimage.map_coordinates(plate, coordinates, order=1, mode="nearest", output=np.float32) >= 0.5
    return out


def _depth_squared(work: np.ndarray) -> np.ndarray:
    """int32, ``work``'s shape: the squared distance (voxels²) of each voxel of ``work`` to the nearest voxel outside
    it (the grid's border is outside), 0 outside: the Euclidean distance transform of the inside voxels only.

    Shell by shell: a voxel with an outside voxel at an offset of squared length ``r²`` and none nearer is ``r²``
    deep (most voxels of a plate a few voxels thick are 1–9 deep); the few deeper than the shells are nearest-point
    queries against the outside voxels that touch the inside (the nearest outside voxel always does). Where numba is
    loaded (:mod:`.volume_kernels`), :func:`.medial_kernels.shell_depths` visits each voxel's offsets up to
    ``KERNEL_SHELL_R2``; else every pending voxel is gathered once per offset up to ``SHELL_R2``. The same
    distances as the queries of every voxel, either way."""
    from .volume_kernels import kernels_in_use

    index = np.flatnonzero(work)
    squared = np.zeros(work.shape, np.int32)
    if kernels_in_use():
        from .medial_kernels import shell_depths

        offsets, lengths = _shell_table(KERNEL_SHELL_R2)
        found = shell_depths(np.ascontiguousarray(work, bool), index, offsets, lengths)
        pending = index[found < 0]
        squared.ravel()[index] = found
    else:
        pending = _shell_depths_gathered(work, index, squared.ravel())
    if len(pending):
        squared.ravel()[pending] = _queried_depths(work, pending)
    return squared


def _shell_depths_gathered(work: np.ndarray, index: np.ndarray, out: np.ndarray) -> np.ndarray:
    """The shells up to ``SHELL_R2`` over the flat ``index`` (C order) of ``work``, every pending voxel gathered once
    per offset (on the grid padded with outside voxels): the depths written to ``out`` (flat, ``work``'s size), the
    flat indices of the voxels deeper than the shells returned."""
    pad = int(np.sqrt(SHELL_R2))
    padded = np.pad(work, pad)
    flat = padded.ravel()
    pending = np.ravel_multi_index([i + pad for i in np.unravel_index(index, work.shape)], padded.shape)
    strides = np.array(padded.strides) // padded.itemsize
    for r2, offsets in _shells(SHELL_R2):
        if len(pending) == 0:
            break
        reached = np.zeros(len(pending), bool)
        for offset in offsets @ strides:
            reached |= ~flat[pending + offset]
        out[np.ravel_multi_index([i - pad for i in np.unravel_index(pending[reached], padded.shape)],
                                 work.shape)] = r2
        pending = pending[~reached]
    return np.ravel_multi_index([i - pad for i in np.unravel_index(pending, padded.shape)], work.shape)


def _queried_depths(work: np.ndarray, pending: np.ndarray) -> np.ndarray:
    """The squared distances (int32) of the flat ``pending`` voxels of ``work`` to the nearest outside voxel that
    touches the inside (the grid's border outside): nearest-point queries."""
    from scipy.spatial import cKDTree

    padded = np.pad(work, 1)
    edge = grown(padded) & ~padded
    deep = np.stack(np.unravel_index(pending, work.shape), axis=1) + 1
    return np.rint(cKDTree(np.argwhere(edge)).query(deep)[0] ** 2).astype(np.int32)


@lru_cache(maxsize=2)
def _shell_table(max_r2: int) -> tuple[np.ndarray, np.ndarray]:
    """:func:`_shells` as one table: offsets ``(M, 3)`` int64, C-contiguous, and their squared lengths ``(M,)``,
    shortest first (the kernel's order)."""
    shells = _shells(max_r2)
    offsets = np.ascontiguousarray(np.concatenate([o for _, o in shells]), np.int64)
    lengths = np.concatenate([np.full(len(o), r2, np.int64) for r2, o in shells])
    return offsets, lengths


def _shells(max_r2: int) -> list[tuple[int, np.ndarray]]:
    """Integer offsets ``(N, 3)`` grouped by squared length ``r²``, for ``1 ≤ r² ≤ max_r2``, shortest first."""
    reach = int(np.sqrt(max_r2))
    grid = np.mgrid[-reach:reach + 1, -reach:reach + 1, -reach:reach + 1].reshape(3, -1).T
    squared = (grid ** 2).sum(1)
    return [(int(r2), grid[squared == r2]) for r2 in np.unique(squared) if 1 <= r2 <= max_r2]


def _nearer_plate(work: np.ndarray, points: np.ndarray, is_plate: np.ndarray) -> np.ndarray:
    """The voxels of ``work`` strictly nearer a plate medial point than a tube one (Euclidean, working voxels).

    Most voxels of a skull's diploë lie within ``SURE_STEPS`` voxels (per axis) of a plate medial point, so within
    ``SURE_STEPS × √3``, and farther than that from every tube point: plate for sure, decided on the grid (two
    maximum filters). The others: where numba is loaded (:mod:`.volume_kernels`), each voxel's offsets in order of
    length up to ``KERNEL_SHELL_R2`` (:func:`.medial_kernels.nearer_marks`); the rest nearest-point queries
    (:func:`_queried_nearer`). The same voxels as comparing both unbounded distances."""
    from .volume_kernels import kernels_in_use

    if not (~is_plate).any():
        return work.copy()
    reach = SURE_STEPS * np.sqrt(3.0)  # the farthest a plate point within SURE_STEPS voxels per axis lies
    near_plate = cube_maximum(_marked(work.shape, points[is_plate]), 2 * SURE_STEPS + 1).view(bool)
    out = work & near_plate
    tubes, steps = points[~is_plate], int(np.ceil(reach))
    low, high = np.maximum(tubes.min(0) - steps, 0), np.minimum(tubes.max(0) + steps + 1, work.shape)
    box = tuple(slice(a, b) for a, b in zip(low, high))  # every voxel within ``reach`` of a tube point (and more)
    near_tube = cube_maximum(_marked(high - low, tubes - low), 2 * steps + 1)
    out[box] &= ~near_tube.view(bool)
    undecided = np.flatnonzero(work & ~out)
    if len(undecided) and kernels_in_use():
        from .medial_kernels import nearer_marks

        marks = _marked(work.shape, points[is_plate]).view(np.int8)
        marks[tuple(tubes.T)] = 2
        nearer = nearer_marks(marks, undecided, *_shell_table(KERNEL_SHELL_R2))
        out.ravel()[undecided[nearer == 1]] = True
        undecided = undecided[nearer < 0]
    if len(undecided):
        voxels = np.stack(np.unravel_index(undecided, work.shape), axis=1)
        out.ravel()[undecided[_queried_nearer(voxels, points, is_plate)]] = True
    return out


def _queried_nearer(voxels: np.ndarray, points: np.ndarray, is_plate: np.ndarray) -> np.ndarray:
    """Whether each voxel ``(N, 3)`` is strictly nearer a plate point than a tube one: nearest-point queries, the
    distance to the tube points first, then the plate points searched no farther than it (a voxel amid the tree is
    about as far from every point of a skull around it, which an unbounded search visits)."""
    from scipy.spatial import cKDTree

    to_tube = cKDTree(points[~is_plate]).query(voxels)[0]
    to_plate = np.full(len(voxels), np.inf)
    plates = cKDTree(points[is_plate])
    bound = np.ceil(to_tube)
    for limit in np.unique(bound):  # a plate point at to_tube or farther is not nearer: not looked for
        chosen = bound == limit
        to_plate[chosen] = plates.query(voxels[chosen], distance_upper_bound=float(limit))[0]
    return to_plate < to_tube


def _marked(shape, points: np.ndarray) -> np.ndarray:
    """uint8 grid of ``shape``: 1 at ``points`` (``(N, 3)`` indices)."""
    grid = np.zeros(shape, np.uint8)
    grid[tuple(points.T)] = 1
    return grid


def _box(mask: np.ndarray, margin: int) -> tuple[np.ndarray, np.ndarray]:
    box = bounding_box(mask, margin)  # not empty (the caller's check)
    return np.array([b.start for b in box]), np.array([b.stop for b in box])


__all__ = ["PLATE_RATIO", "WORK_MM", "MedialShape", "medial_points", "medial_ratio", "medial_shape", "to_working_grid",
           "working_mm"]
