"""Which voxels lie within a distance (mm) of a mask: the band test of the volume readers, at a bounded memory.

``within_mm(mask, spacing_mm, band_mm)`` is the set ``distance_transform_edt(~mask, sampling=spacing_mm) <=
band_mm`` (voxel centres, Euclidean, per-axis spacing), computed without the full-grid transform: a full
``scipy.ndimage.distance_transform_edt`` holds ~60 bytes per voxel at its peak (an int32 feature transform, an
int32 index grid, their float64 difference), 5 GB for a 0.3 mm head. Here:

* only the mask's bounding box grown by the band is transformed (a voxel outside it is farther than the band
  along one axis);
* a band a few voxels wide (at most ``MAX_BALL_ROWS`` rows of voxels across its ellipsoid) is a dilation: the
  mask dilated along the last axis by each row's half-width, shifted by the row's offset (the ellipsoid's offsets
  chosen by the distance formed as below), a few dozen boolean passes;
* a wider band: the box is cut into slabs along the first axis, each transformed with a halo of ``ceil(band / spacing[0])``
  slices (and one more) on both sides. A voxel within the band of the mask has its nearest mask voxel within the halo, so its
  slab's distance is the true one; a voxel beyond the band is at least as far from the slab's mask voxels. The
  set is therefore identical to the full transform's;
* a slab's distances are the separable exact transform of :mod:`.distance_kernels` (numba; ~4 × faster than
  scipy's feature transform, 8 bytes a voxel), summed with the same float64 operations in the same order as
  scipy's (``(feature - index) × spacing``, squared, summed over the axes, square root), so the band's edge falls
  where it does there (a voxel exactly as far from two mask voxels, the two sums differing in the last bit and
  the band between them, is the only way to differ; none in the tests' ties).
"""

from __future__ import annotations

import numpy as np

SLAB_VOXELS = 2_000_000  # voxels of a slab's core (its halo comes on top): ~30 bytes each at the peak
MAX_BALL_ROWS = 160  # a band of at most this many rows of voxels across is dilated directly (a few voxels wide)


def within_mm(mask: np.ndarray, spacing_mm, band_mm: float) -> np.ndarray:
    """bool, ``mask``'s shape: the voxels whose centre lies within ``band_mm`` of a voxel of ``mask`` (bool)."""
    spacing = np.asarray(spacing_mm, np.float64)
    out = np.zeros(mask.shape, bool)
    box = _grown_box(mask, spacing, band_mm)
    if box is None:
        return out
    pairs = _ball_rows(spacing, band_mm)
    if len(pairs) <= MAX_BALL_ROWS:
        region = tuple(slice(a, b) for a, b in zip(*box))
        out[region] = _ball_within(mask[region], pairs)
        return out
    (low, high), halo = box, int(np.ceil(band_mm / spacing[0])) + 1
    area = int(np.prod(high[1:] - low[1:]))
    core = max(2 * halo, SLAB_VOXELS // max(area, 1))  # a wide band's halo is at most the slab's core
    for start in range(low[0], high[0], core):
        stop = min(start + core, high[0])
        first, last = max(start - halo, 0), min(stop + halo, mask.shape[0])
        part = mask[first:last, low[1]:high[1], low[2]:high[2]]
        if not part.any():
            continue
        near = _slab_within(part, spacing, band_mm)
        out[start:stop, low[1]:high[1], low[2]:high[2]] = near[start - first:stop - first]
    return out


def _grown_box(mask: np.ndarray, spacing: np.ndarray, band_mm: float):
    """``(low, high)`` voxel bounds of ``mask``'s voxels grown by ``band_mm``, clipped to the grid; None if empty."""
    hits = [np.flatnonzero(mask.any(axis=tuple(b for b in range(3) if b != a))) for a in range(3)]
    if any(len(h) == 0 for h in hits):
        return None
    reach = np.ceil(band_mm / spacing).astype(int) + 1
    low = np.maximum(np.array([h[0] for h in hits]) - reach, 0)
    high = np.minimum(np.array([h[-1] for h in hits]) + reach + 1, mask.shape)
    return low, high


def _ball_rows(spacing: np.ndarray, band_mm: float) -> list[tuple[int, int, int]]:
    """The band's ellipsoid as rows along the last axis: ``(di, dj, w)``, offsets ``(di, dj, -w…w)`` in voxels,
    each offset's distance formed as scipy forms it (``((di s0)² + (dj s1)²) + (dk s2)²``, then its root)."""
    reach = np.ceil(band_mm / spacing).astype(int) + 1
    rows = []
    for di in range(-reach[0], reach[0] + 1):
        for dj in range(-reach[1], reach[1] + 1):
            a, b = float(di) * spacing[0], float(dj) * spacing[1]
            w = -1
            for dk in range(reach[2] + 1):
                c = float(dk) * spacing[2]
                if np.sqrt((a * a + b * b) + c * c) > band_mm:
                    break
                w = dk
            if w >= 0:
                rows.append((di, dj, w))
    return rows


def _ball_within(mask: np.ndarray, rows: list[tuple[int, int, int]]) -> np.ndarray:
    """``mask`` dilated by the ellipsoid ``rows``: per half-width ``w``, the mask dilated along the last axis by
    ``w``, then shifted by each row's ``(di, dj)`` (a few dozen boolean passes for a band of a few voxels)."""
    from scipy import ndimage

    out = np.zeros(mask.shape, bool)
    for w in sorted({row[2] for row in rows}):
        along = ndimage.maximum_filter1d(mask.view(np.uint8), 2 * w + 1, axis=2, mode="constant").view(bool)
        for di, dj, _ in (row for row in rows if row[2] == w):
            target = tuple(slice(max(-d, 0), n - max(d, 0)) for d, n in zip((di, dj), mask.shape[:2]))
            source = tuple(slice(max(d, 0), n - max(-d, 0)) for d, n in zip((di, dj), mask.shape[:2]))
            np.logical_or(out[target], along[source], out=out[target])
    return out


def _slab_within(part: np.ndarray, spacing: np.ndarray, band_mm: float) -> np.ndarray:
    """``distance_transform_edt(~part, sampling=spacing) <= band_mm``: the squared distances of
    :func:`.distance_kernels.squared_distances` (scipy's sums, in its order), their root compared."""
    from .distance_kernels import squared_distances
    from .volume_kernels import kernels_ready

    kernels_ready()
    squared = np.empty(part.shape)
    squared_distances(np.ascontiguousarray(part, bool), float(spacing[0]), float(spacing[1]), float(spacing[2]),
                      squared)
    return np.sqrt(squared, out=squared) <= band_mm


__all__ = ["within_mm"]
