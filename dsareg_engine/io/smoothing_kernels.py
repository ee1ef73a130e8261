"""A volume's Gaussian smoothing of half a voxel (numba, cached on disk): ``scipy.ndimage.gaussian_filter(voxels,
0.5)``'s float32 values, bit for bit, at about half its CPU on a head's grid.

scipy correlates one axis after the other (0, 1, 2), each line in float64 with ``mode="reflect"`` (``d c b a | a b
c d``), the five weights of ``exp(−x² / 2σ²)`` normalised (``truncate`` 4: a radius of 2 voxels), the symmetric
pairs summed first (``c·w0 + (a + e)·w2 + (b + d)·w1``, in that order), and rounds each axis's result to float32.
:func:`smoothed` does the same operations in the same order; it works along axis 0 plane by plane and along axis 1
row by row, so the innermost loop runs along contiguous memory, and reads a volume stored slice by slice (a DICOM
series' Fortran-ordered grid) in tiles.
"""

from __future__ import annotations

import numpy as np
from numba import njit

SMOOTHED_SIGMA_VOX = 0.5  # the one width :func:`smoothed` computes itself (others: scipy)


def smoothed(voxels: np.ndarray, sigma_vox: float) -> np.ndarray:
    """``ndimage.gaussian_filter(voxels, sigma_vox)`` (a new C-ordered array of ``voxels``' type and shape)."""
    weights = _weights(sigma_vox)
    if voxels.dtype != np.float32 or voxels.ndim != 3 or len(weights) != 3 or min(voxels.shape) < 1:
        from scipy import ndimage

        return ndimage.gaussian_filter(voxels, sigma_vox)
    w0, w1, w2 = (float(w) for w in weights)
    out = np.empty(voxels.shape, np.float32)
    if voxels.strides[0] < voxels.strides[2]:  # axis 0 is the fastest: a series' grid (or a box of it)
        _first_axis_fortran(voxels, out, w0, w1, w2)
    else:
        _first_axis(voxels, out, w0, w1, w2)
    _second_axis(out, w0, w1, w2)
    _third_axis(out, w0, w1, w2)
    return out


def _weights(sigma_vox: float) -> np.ndarray:
    """The centre and one side of scipy's Gaussian weights (``truncate`` 4), as scipy computes them."""
    radius = int(4.0 * float(sigma_vox) + 0.5)
    x = np.arange(-radius, radius + 1)
    phi = np.exp(-0.5 / (float(sigma_vox) * float(sigma_vox)) * x ** 2)
    phi = phi / phi.sum()
    return phi[radius:]


@njit(cache=True)
def _reflect(i, n):
    while i < 0 or i >= n:
        if i < 0:
            i = -i - 1
        if i >= n:
            i = 2 * n - i - 1
    return i


@njit(cache=True)
def _rows(src, n, w0, w1, w2, dst):
    """``dst[t] = src[t]·w0 + (src[t−2] + src[t+2])·w2 + (src[t−1] + src[t+1])·w1`` for each row ``t < n`` of the
    2D ``src`` (float64 sums, reflected rows at the ends), rounded to float32."""
    for t in range(n):
        a, b, c = src[_reflect(t - 2, n)], src[_reflect(t - 1, n)], src[t]
        d, e, out = src[_reflect(t + 1, n)], src[_reflect(t + 2, n)], dst[t]
        for k in range(src.shape[1]):
            total = np.float64(c[k]) * w0
            total += (np.float64(a[k]) + np.float64(e[k])) * w2
            total += (np.float64(b[k]) + np.float64(d[k])) * w1
            out[k] = np.float32(total)


@njit(cache=True)
def _at(line, t, n, w0, w1, w2):
    total = np.float64(line[t]) * w0
    total += (np.float64(line[_reflect(t - 2, n)]) + np.float64(line[_reflect(t + 2, n)])) * w2
    total += (np.float64(line[_reflect(t - 1, n)]) + np.float64(line[_reflect(t + 1, n)])) * w1
    return np.float32(total)


@njit(cache=True)
def _line(line, n, w0, w1, w2, out):
    """One line's values (:func:`_rows`' sums along it); the ends reflected, the inside without index tests."""
    for t in range(min(2, n)):
        out[t] = _at(line, t, n, w0, w1, w2)
    for t in range(2, n - 2):
        total = np.float64(line[t]) * w0
        total += (np.float64(line[t - 2]) + np.float64(line[t + 2])) * w2
        total += (np.float64(line[t - 1]) + np.float64(line[t + 1])) * w1
        out[t] = np.float32(total)
    for t in range(max(2, n - 2), n):
        out[t] = _at(line, t, n, w0, w1, w2)


@njit(cache=True)
def _first_axis_fortran(src, dst, w0, w1, w2):
    """``dst`` = ``src`` along axis 0, ``src``'s axis 0 its fastest: each plane ``[:, j, :]`` gathered in tiles."""
    n0, n1, n2 = src.shape
    plane = np.empty((n0, n2), np.float32)
    for j in range(n1):
        for k0 in range(0, n2, 16):
            for i0 in range(0, n0, 64):
                for k in range(k0, min(k0 + 16, n2)):
                    for i in range(i0, min(i0 + 64, n0)):
                        plane[i, k] = src[i, j, k]
        _rows(plane, n0, w0, w1, w2, dst[:, j, :])


@njit(cache=True)
def _first_axis(src, dst, w0, w1, w2):
    """``dst`` = ``src`` along axis 0 (a C-ordered ``src``, or a box of one)."""
    n0, n1, n2 = src.shape
    plane = np.empty((n0, n2), np.float32)
    for j in range(n1):
        for i in range(n0):
            for k in range(n2):
                plane[i, k] = src[i, j, k]
        _rows(plane, n0, w0, w1, w2, dst[:, j, :])


@njit(cache=True)
def _second_axis(grid, w0, w1, w2):
    """``grid`` (C order) along axis 1, in place (each plane copied first)."""
    n0, n1, n2 = grid.shape
    plane = np.empty((n1, n2), np.float32)
    for i in range(n0):
        plane[:, :] = grid[i]
        _rows(plane, n1, w0, w1, w2, grid[i])


@njit(cache=True)
def _third_axis(grid, w0, w1, w2):
    """``grid`` (C order) along axis 2, in place (each line copied first)."""
    n0, n1, n2 = grid.shape
    line = np.empty(n2, np.float32)
    for i in range(n0):
        for j in range(n1):
            line[:] = grid[i, j]
            _line(line, n2, w0, w1, w2, grid[i, j])


KERNELS = (_first_axis_fortran, _first_axis, _second_axis, _third_axis)


def compile_smoothing_kernels() -> None:
    """The kernels compiled (or loaded from numba's cache) with the types a reading passes: a float32 grid as
    series, NIfTI and MetaImage volumes store it (C or Fortran order), whole or a box of it."""
    for order in "FC":
        grid = np.zeros((4, 4, 4), np.float32, order=order)
        smoothed(grid, SMOOTHED_SIGMA_VOX)
        smoothed(grid[1:, 1:, 1:], SMOOTHED_SIGMA_VOX)
"""The dispatchers :func:`smoothed` calls (the warm-up's ``volumes`` group checks they are cached)."""

__all__ = ["KERNELS", "SMOOTHED_SIGMA_VOX", "compile_smoothing_kernels", "smoothed"]
