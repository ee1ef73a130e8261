"""The plate search's kernels (:mod:`.medial_shape`, :mod:`.bone_plates`; numba, cached on disk), each giving the
values of the numpy / scipy computation it replaces, at the voxels inside the measured mask only (a twentieth of its
working grid on a skull's diploë):

* :func:`maxima_at`: the values of ``scipy.ndimage.maximum_filter(values, size, mode="reflect")`` at chosen voxels
  (a reflected index lies inside the window, so the window clipped to the grid holds the same values): the depth's
  local tops, two cube sides in one visit of each voxel's neighbourhood (two whole-grid filters took ~2.4 × as long);
* :func:`shell_depths`: the squared distance of each inside voxel to the nearest voxel outside the mask or the grid,
  by offsets in order of length: the depth shell by shell, one voxel at a time (the numpy shells gather every
  pending voxel once per offset; a diploë 6 mm thick sends ~10 % of its voxels past them to nearest-point queries);
* :func:`nearer_marks`: whether a voxel's nearest medial point is a plate point (and no tube point as near), by the
  same offsets: the plate parts' undecided voxels (nearest-point queries of two trees before);
* :func:`corner_agreement`: whether a mask voxel's eight interpolation corners on the working grid agree: the
  plate back on the mask is interpolated (``map_coordinates``) only where they do not;
* :func:`ball_counts`: the mask voxels within a ball around each sampled medial point (``cKDTree.query_ball_point``'s
  counts, distance ≤ radius), each of the ball's rows from the grid's running sums along its last axis;
* :func:`surface_contact`: a plate part's surface voxels and those touching bone, one visit of its box (a gather of
  the part's voxels per face neighbour before).
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True)
def _voxel(flat, n1, n2):
    """The indices ``(i, j, k)`` of C-order flat index ``flat`` on a grid of ``(·, n1, n2)``."""
    i, rest = flat // (n1 * n2), flat % (n1 * n2)
    return i, rest // n2, rest % n2


@njit(cache=True)
def maxima_at(values, index, half_outer, half_inner):
    """For each flat ``index`` (C order, ascending) of ``values`` (3D, C order): the maximum over the cube of
    ``2 half_outer + 1`` voxels a side centred on it and over the cube of ``2 half_inner + 1`` (``half_inner ≤
    half_outer``), each clipped to the grid. Two arrays of ``values``' type, ``index``'s length. Each cube is the
    maximum of its columns along the last axis (a column: the maximum over the cube's square across the first two
    axes at one position of the last); a run of chosen voxels along the last axis reuses the columns it shares, so
    each voxel of a run reads one new column, not the whole cube."""
    n0, n1, n2 = values.shape
    outer = np.empty(len(index), values.dtype)
    inner = np.empty(len(index), values.dtype)
    width = 2 * half_outer + 1
    outer_columns = np.empty(width, values.dtype)  # by position of the last axis modulo ``width``
    inner_columns = np.empty(width, values.dtype)
    row, first, last = -1, 0, -1  # the row (flat index over the first two axes) whose columns first … last are made
    for n in range(len(index)):
        flat = index[n]
        here_row, k = flat // n2, flat % n2
        i, j = here_row // n1, here_row % n1
        start, stop = max(k - half_outer, 0), min(k + half_outer + 1, n2)
        if here_row != row or start < max(first, last - width + 1) or start > last + 1:
            row, first, last = here_row, start, start - 1  # nothing to reuse: a new run
        for c in range(last + 1, stop):
            best_outer = values[i, j, c]
            best_inner = best_outer
            for a in range(max(i - half_outer, 0), min(i + half_outer + 1, n0)):
                near_a = abs(a - i) <= half_inner
                for b in range(max(j - half_outer, 0), min(j + half_outer + 1, n1)):
                    value = values[a, b, c]
                    best_outer = max(best_outer, value)
                    if near_a and abs(b - j) <= half_inner:
                        best_inner = max(best_inner, value)
            outer_columns[c % width] = best_outer
            inner_columns[c % width] = best_inner
        last = max(last, stop - 1)
        best_outer = outer_columns[start % width]
        best_inner = values[i, j, k]
        for c in range(start, stop):
            best_outer = max(best_outer, outer_columns[c % width])
            if abs(c - k) <= half_inner:
                best_inner = max(best_inner, inner_columns[c % width])
        outer[n] = best_outer
        inner[n] = best_inner
    return outer, inner


@njit(cache=True)
def shell_depths(inside, index, offsets, squared_lengths):
    """For each flat ``index`` (C order) of the bool grid ``inside`` (3D, C order): the squared length of its
    shortest offset (``offsets`` ``(M, 3)``, sorted by ``squared_lengths`` ``(M,)``, shortest first) that lands
    outside ``inside`` or outside the grid; ``-1`` where every offset lands inside. int32, ``index``'s length."""
    n0, n1, n2 = inside.shape
    out = np.full(len(index), -1, np.int32)
    for n in range(len(index)):
        i, j, k = _voxel(index[n], n1, n2)
        for m in range(len(offsets)):
            a, b, c = i + offsets[m, 0], j + offsets[m, 1], k + offsets[m, 2]
            if a < 0 or a >= n0 or b < 0 or b >= n1 or c < 0 or c >= n2 or not inside[a, b, c]:
                out[n] = squared_lengths[m]
                break
    return out


@njit(cache=True)
def nearer_marks(marks, index, offsets, squared_lengths):
    """For each flat ``index`` (C order) of the int8 grid ``marks`` (3D, C order; 1: a plate medial point, 2: a
    tube one, 0: none): 1 where its nearest marked voxel (itself, else by ``offsets`` ``(M, 3)`` in order of
    ``squared_lengths``, shortest first; outside the grid is unmarked) is a plate point and no tube point is as
    near, 0 where a tube point is at least as near, ``-1`` where no offset reaches a mark. int8, ``index``'s
    length."""
    n0, n1, n2 = marks.shape
    out = np.full(len(index), -1, np.int8)
    for n in range(len(index)):
        i, j, k = _voxel(index[n], n1, n2)
        if marks[i, j, k] != 0:  # a medial point itself: its own mark is the nearest
            out[n] = 1 if marks[i, j, k] == 1 else 0
            continue
        found, plate, tube = -1, False, False
        for m in range(len(offsets)):
            if found >= 0 and squared_lengths[m] > found:
                break
            a, b, c = i + offsets[m, 0], j + offsets[m, 1], k + offsets[m, 2]
            if a < 0 or a >= n0 or b < 0 or b >= n1 or c < 0 or c >= n2:
                continue
            mark = marks[a, b, c]
            if mark == 0:
                continue
            found = squared_lengths[m]
            plate |= mark == 1
            tube |= mark == 2
        if found >= 0:
            out[n] = 1 if plate and not tube else 0
    return out




@njit(cache=True)
def corner_agreement(grid, index, shape, corners_0, corners_1, corners_2):
    """For each flat ``index`` (C order) of a box of ``shape`` whose voxels interpolate the 0/1 ``grid`` (3D) between
    the corners ``corners_a[i] … corners_a[i] + 1`` on axis ``a`` (an index past the grid's last clamped to it):
    1 where all eight corners are 1, 0 where none is, ``-1`` where they differ. int8, ``index``'s length."""
    n0, n1, n2 = grid.shape
    out = np.empty(len(index), np.int8)
    for n in range(len(index)):
        i, j, k = _voxel(index[n], shape[1], shape[2])
        a, b, c = corners_0[i], corners_1[j], corners_2[k]
        ones = 0
        for a_ in (a, min(a + 1, n0 - 1)):
            for b_ in (b, min(b + 1, n1 - 1)):
                for c_ in (c, min(c + 1, n2 - 1)):
                    ones += 1 if grid[a_, b_, c_] else 0
        out[n] = 1 if ones == 8 else (0 if ones == 0 else -1)
    return out


@njit(cache=True)
def ball_counts(inside, points, radii, half_radii):
    """The voxels of the bool grid ``inside`` (3D, C order) within ``radii`` and within ``half_radii`` (Euclidean,
    voxels; distance ≤ radius, squared distances against the radius squared) of each point ``(N, 3)`` (integer
    voxel indices): each row of a ball is counted from the row's running sums (uint16: rows shorter than 65,535
    voxels). Two int64 arrays of ``N``."""
    n0, n1, n2 = inside.shape
    running = np.zeros((n0, n1, n2 + 1), np.uint16)
    for a in range(n0):
        for b in range(n1):
            for c in range(n2):
                running[a, b, c + 1] = running[a, b, c] + (1 if inside[a, b, c] else 0)
    outer = _counts_within(running, points, radii)
    return outer, _counts_within(running, points, half_radii)


@njit(cache=True)
def _counts_within(running, points, radii):
    n0, n1, n2 = running.shape[0], running.shape[1], running.shape[2] - 1
    counts = np.zeros(len(points), np.int64)
    for n in range(len(points)):
        i, j, k = points[n, 0], points[n, 1], points[n, 2]
        limit = radii[n] * radii[n]
        reach = int(np.floor(radii[n]))
        total = 0
        for a in range(max(i - reach, 0), min(i + reach + 1, n0)):
            for b in range(max(j - reach, 0), min(j + reach + 1, n1)):
                across = (a - i) * (a - i) + (b - j) * (b - j)  # exact integers, compared as scipy does
                if float(across) > limit:
                    continue
                half = int(np.sqrt(max(limit - across, 0.0)))
                while float(across + (half + 1) * (half + 1)) <= limit:
                    half += 1
                while half > 0 and float(across + half * half) > limit:
                    half -= 1
                low, high = max(k - half, 0), min(k + half + 1, n2)
                if high > low:
                    total += running[a, b, high] - running[a, b, low]
        counts[n] = total
    return counts



@njit(cache=True)
def surface_contact(labels, index, low, high, bone):
    """Part ``index`` of ``labels`` (3D, C order; its box ``low`` … ``high``, three ints each): its surface voxels (a
    face neighbour outside the part; the grid's border is no neighbour) and those of them with a face neighbour
    outside the part in ``bone`` (bool, ``labels``' shape). Two ints."""
    shape = labels.shape
    surface = touching = 0
    for i in range(low[0], high[0]):
        for j in range(low[1], high[1]):
            for k in range(low[2], high[2]):
                if labels[i, j, k] != index:
                    continue
                on_surface = against = False
                for axis in range(3):
                    for step in (-1, 1):
                        a, b, c = i, j, k
                        if axis == 0:
                            a += step
                        elif axis == 1:
                            b += step
                        else:
                            c += step
                        if a < 0 or b < 0 or c < 0 or a >= shape[0] or b >= shape[1] or c >= shape[2]:
                            continue
                        if labels[a, b, c] != index:
                            on_surface = True
                            against |= bone[a, b, c]
                surface += on_surface
                touching += against
    return surface, touching


def compile_medial_kernels() -> None:
    """Every kernel here compiled (or loaded from numba's cache) with the argument types the readings pass: int32
    depths, int64 flat indices and offset tables, int8 marks, a uint8 plate grid, float64 radii, 16- and 32-bit
    labels (:func:`.voxel_steps.labelled`)."""
    index, cube = np.flatnonzero(np.ones(8, bool)), np.ones((2, 2, 2), bool)
    maxima_at(np.zeros((2, 2, 2), np.int32), index, 2, 1)
    table = (np.zeros((1, 3), np.int64), np.ones(1, np.int64))
    shell_depths(cube, index, *table)
    nearer_marks(np.ones((2, 2, 2), np.int8), index, *table)
    corners = np.zeros(2, np.int64)
    corner_agreement(np.ones((2, 2, 2), np.uint8), index, np.full(3, 2, np.int64), corners, corners, corners)
    ball_counts(cube, np.zeros((1, 3), np.int64), np.ones(1), np.ones(1))
    for labels in (np.uint16, np.int32):
        surface_contact(np.ones((2, 2, 2), labels), 1, np.zeros(3, np.int64), np.full(3, 2, np.int64), cube)


MEDIAL_KERNELS = (maxima_at, shell_depths, nearer_marks, corner_agreement, ball_counts, surface_contact)
"""The dispatchers of this module (the warm-up's ``volumes`` group)."""

__all__ = ["MEDIAL_KERNELS", "ball_counts", "compile_medial_kernels", "corner_agreement", "maxima_at", "nearer_marks", "shell_depths",
           "surface_contact"]
