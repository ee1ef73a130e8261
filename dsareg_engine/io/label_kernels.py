"""Connected components of a 3D mask by its runs (numba, cached on disk): ``scipy.ndimage.label``'s labels (face
neighbours, components numbered 1, 2, … in the raster order of their first voxel), found from the mask's runs
along the last axis rather than voxel by voxel.

A volume reading labels boxes of a whole head (~40 M voxels) that hold a few million mask voxels in a few hundred
thousand runs: scipy's two passes visit every voxel of the box (~0.16 s a box); here one pass finds the runs, the
runs of neighbouring rows are joined (union–find, each component's root its first run), and the labels are
written run by run. :func:`runs_labelled` gives up (``None``: the caller labels with scipy) on a mask of more runs
than ``MAX_RUN_SHARE`` of its voxels (a noise-like mask: the run tables would outgrow scipy's memory).
:func:`component_runs` stops before the labels are written: a component's size and which components to keep need
only the runs, and a 600-slice head's box labelled in 16 bits is 0.26 GB.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit

MAX_RUN_SHARE = 0.125  # runs per voxel of the box beyond which scipy labels instead (16 bytes a run)
UINT16_LABELS = 65_535  # the most components 16-bit labels hold


@dataclass(frozen=True)
class ComponentRuns:
    """A 3D mask's runs along its last axis and each run's component (``ndimage.label``'s numbering)."""

    shape: tuple[int, ...]
    row_first: np.ndarray  # (n0 n1 + 1,) int64: the first run of each row i n1 + j, the rows in raster order
    starts: np.ndarray  # (runs,) int32: last-axis position of each run's first voxel
    stops: np.ndarray  # (runs,) int32: and one past its last
    labels: np.ndarray  # (runs,) int64: the component of each run, 1 … count
    count: int

    def sizes(self) -> np.ndarray:
        """Voxels per component ``0 … count`` (int64; 0: the background's, as ``label_sizes`` counts it)."""
        sizes = _run_sizes(self.labels, self.starts, self.stops, self.count)
        sizes[0] = int(np.prod(self.shape)) - int(sizes[1:].sum())
        return sizes

    def touching(self, near: np.ndarray) -> np.ndarray:
        """bool per component ``0 … count``: whether one of its voxels is in ``near`` (bool, the mask's shape)."""
        return _touching(np.asarray(near, bool), self.row_first, self.starts, self.stops, self.labels, self.count)

    def write(self, out: np.ndarray, chosen: np.ndarray) -> None:
        """``out[...] = chosen[labels]`` where the mask was (``out`` bool, the mask's shape, zero elsewhere;
        ``chosen[0]``, the background's, is not written)."""
        _written(out, self.row_first, self.starts, self.stops, np.asarray(chosen, bool)[self.labels])


def component_runs(mask: np.ndarray) -> ComponentRuns | None:
    """The components of a 3D bool ``mask`` by its runs, no label grid written; ``None`` when the mask has too many
    runs (label it with scipy)."""
    mask = np.asarray(mask, bool)  # a box of a larger grid is read in place (numba takes any layout)
    runs = _run_count(mask)
    if runs > MAX_RUN_SHARE * mask.size:
        return None
    row_first, starts, stops = _runs(mask, runs)
    run_labels, count = _run_labels(mask.shape[1], row_first, starts, stops)
    return ComponentRuns(tuple(mask.shape), row_first, starts, stops, run_labels, int(count))


def runs_labelled(mask: np.ndarray, narrow: bool = False) -> tuple[np.ndarray, int] | None:
    """``ndimage.label(mask)`` of a 3D bool ``mask``: ``(labels, count)``, int32 labels, or uint16 with ``narrow``
    where the count fits (scipy's ``output=np.uint16``); ``None`` when the mask has too many runs (label it with
    scipy)."""
    found = component_runs(mask)
    if found is None:
        return None
    labels = np.zeros(found.shape, np.uint16 if narrow and found.count <= UINT16_LABELS else np.int32)
    _written(labels, found.row_first, found.starts, found.stops, found.labels)
    return labels, found.count


@njit(cache=True)
def _run_count(mask):
    n0, n1, n2 = mask.shape
    count = 0
    for i in range(n0):
        for j in range(n1):
            before = False
            for k in range(n2):
                here = mask[i, j, k]
                if here and not before:
                    count += 1
                before = here
    return count


@njit(cache=True)
def _runs(mask, count):
    """The runs along the last axis: ``row_first`` (``n0 n1 + 1``: the first run of each row ``i n1 + j``, the
    rows in raster order), each run's ``starts`` and ``stops`` (last-axis positions, stop exclusive)."""
    n0, n1, n2 = mask.shape
    row_first = np.zeros(n0 * n1 + 1, np.int64)
    starts = np.empty(count, np.int32)
    stops = np.empty(count, np.int32)
    run = 0
    for i in range(n0):
        for j in range(n1):
            row_first[i * n1 + j] = run
            k = 0
            while k < n2:
                if mask[i, j, k]:
                    starts[run] = k
                    while k < n2 and mask[i, j, k]:
                        k += 1
                    stops[run] = k
                    run += 1
                else:
                    k += 1
    row_first[n0 * n1] = run
    return row_first, starts, stops


@njit(cache=True)
def _root(parent, run):
    while parent[run] != run:
        parent[run] = parent[parent[run]]  # path halving
        run = parent[run]
    return run


@njit(cache=True)
def _joined(parent, row, other, row_first, starts, stops):
    """Join each run of ``row`` with the runs of ``other`` (a neighbouring row, earlier in raster order) it
    overlaps on the last axis: face neighbours. The root of a component stays its earliest run."""
    first = row_first[other]
    last = row_first[other + 1]
    for run in range(row_first[row], row_first[row + 1]):
        while first < last and stops[first] <= starts[run]:
            first += 1
        near = first
        while near < last and starts[near] < stops[run]:
            a, b = _root(parent, run), _root(parent, near)
            if a != b:
                parent[max(a, b)] = min(a, b)
            near += 1


@njit(cache=True)
def _run_labels(n1, row_first, starts, stops):
    """Each run's component label, numbered in the order of each component's first run; and the count."""
    rows = len(row_first) - 1
    parent = np.arange(len(starts))
    for row in range(rows):
        if row_first[row] == row_first[row + 1]:
            continue
        if row % n1 > 0:
            _joined(parent, row, row - 1, row_first, starts, stops)
        if row >= n1:
            _joined(parent, row, row - n1, row_first, starts, stops)
    labels = np.empty(len(starts), np.int64)
    count = 0
    for run in range(len(starts)):
        root = _root(parent, run)
        if root == run:
            count += 1
            labels[run] = count
        else:
            labels[run] = labels[root]
    return labels, count


@njit(cache=True)
def _written(out, row_first, starts, stops, run_labels):
    n1 = out.shape[1]
    for row in range(len(row_first) - 1):
        i, j = row // n1, row % n1
        for run in range(row_first[row], row_first[row + 1]):
            out[i, j, starts[run]:stops[run]] = run_labels[run]


@njit(cache=True)
def _run_sizes(run_labels, starts, stops, count):
    sizes = np.zeros(count + 1, np.int64)
    for run in range(len(run_labels)):
        sizes[run_labels[run]] += stops[run] - starts[run]
    return sizes


@njit(cache=True)
def _touching(near, row_first, starts, stops, run_labels, count):
    found = np.zeros(count + 1, np.bool_)
    n1 = near.shape[1]
    for row in range(len(row_first) - 1):
        i, j = row // n1, row % n1
        for run in range(row_first[row], row_first[row + 1]):
            if found[run_labels[run]]:
                continue
            for k in range(starts[run], stops[run]):
                if near[i, j, k]:
                    found[run_labels[run]] = True
                    break
    return found


LABEL_KERNELS = (_run_count, _runs, _run_labels, _written, _run_sizes, _touching)
"""The dispatchers of this module (the warm-up's ``volumes`` group)."""


def compile_label_kernels() -> None:
    """Every kernel here compiled (or loaded from numba's cache) with the types the readings pass: 16- and 32-bit
    labels."""
    mask = np.zeros((2, 3, 20), bool)  # few runs a voxel: under MAX_RUN_SHARE, so every kernel runs
    mask[:, :, 2:9] = True
    mask[0, 1, 5] = False
    for narrow in (False, True):
        for grid in (mask, mask[:, :, 1:]):  # a whole grid and a box of a larger one
            assert runs_labelled(grid, narrow) is not None
    for grid in (mask, mask[:, :, 1:]):  # the kept components sized and written into a grid and into a box of one
        found = component_runs(grid)
        for out, box in ((np.zeros(grid.shape, bool), np.s_[:]), (np.zeros((2, 3, 22), bool), np.s_[:, :, 1:-1])):
            found.write(out[box][:, :, :grid.shape[2]], np.ones(found.count + 1, bool))
            assert found.sizes()[1:].sum() == np.count_nonzero(out) == np.count_nonzero(grid)
        assert found.touching(grid)[1:].all() and not found.touching(np.zeros(grid.shape, bool)).any()


__all__ = ["LABEL_KERNELS", "MAX_RUN_SHARE", "ComponentRuns", "compile_label_kernels", "component_runs", "runs_labelled"]
