"""Numba kernels of the initial-pose search: project many rotated copies of a point set.

Each candidate ``b`` places the centred points ``p`` (``(N, 3)``) at ``M_b p + o_b`` in a
view frame (``M_b`` = world_to_view rotation · candidate rotation, ``o_b`` its position in
the view frame) and projects them with ``u = u0 + fx x / z``, ``v = v0 + fy y / z`` (the
convention of :mod:`dsareg_engine.geometry.rig`). Candidates are split over threads.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from ...render import kernels_numba  # noqa: F401  (sets the non-spinning threading layer first)


@njit(parallel=True, cache=True, fastmath=True)
def mean_pixels(points, turns, offsets, intrinsics, out):
    """out[b] = mean ``(u, v)`` of the projected points. points (N, 3); turns (B, 3, 3); offsets (B, 3);
    intrinsics (fx, fy, u0, v0); out (B, 2)."""
    fx, fy, u0, v0 = intrinsics[0], intrinsics[1], intrinsics[2], intrinsics[3]
    for b in prange(turns.shape[0]):
        m = turns[b]
        su = 0.0
        sv = 0.0
        for n in range(points.shape[0]):
            px, py, pz = points[n, 0], points[n, 1], points[n, 2]
            x = m[0, 0] * px + m[0, 1] * py + m[0, 2] * pz + offsets[b, 0]
            y = m[1, 0] * px + m[1, 1] * py + m[1, 2] * pz + offsets[b, 1]
            z = max(m[2, 0] * px + m[2, 1] * py + m[2, 2] * pz + offsets[b, 2], 1.0)
            su += u0 + fx * x / z
            sv += v0 + fy * y / z
        out[b, 0] = su / points.shape[0]
        out[b, 1] = sv / points.shape[0]


@njit(parallel=True, cache=True, fastmath=True)
def splat_overlap(points, turns, offsets, intrinsics, target, out):
    """out[b] = (Σ target over the distinct pixels the points hit, number of such pixels).

    target (H, W) float32; out (B, 2) float64. A pixel is hit when a point's rounded
    ``(u, v)`` falls on it; points outside the window count nothing.
    """
    fx, fy, u0, v0 = intrinsics[0], intrinsics[1], intrinsics[2], intrinsics[3]
    height, width = target.shape
    for b in prange(turns.shape[0]):
        hit = np.zeros((height, width), dtype=np.uint8)
        m = turns[b]
        overlap = 0.0
        count = 0.0
        for n in range(points.shape[0]):
            px, py, pz = points[n, 0], points[n, 1], points[n, 2]
            x = m[0, 0] * px + m[0, 1] * py + m[0, 2] * pz + offsets[b, 0]
            y = m[1, 0] * px + m[1, 1] * py + m[1, 2] * pz + offsets[b, 1]
            z = max(m[2, 0] * px + m[2, 1] * py + m[2, 2] * pz + offsets[b, 2], 1.0)
            col = int(np.floor(u0 + fx * x / z + 0.5))
            row = int(np.floor(v0 + fy * y / z + 0.5))
            if col >= 0 and col < width and row >= 0 and row < height and hit[row, col] == 0:
                hit[row, col] = 1
                overlap += target[row, col]
                count += 1.0
        out[b, 0] = overlap
        out[b, 1] = count


@njit(parallel=True, cache=True, fastmath=True)
def splat_images(points, turns, offsets, intrinsics, reach, out):
    """out[b] = 1 on the pixels within ``reach`` px (a square) of a point of candidate ``b``, 0 elsewhere.

    out (B, H, W) float32, overwritten; points outside the image count nothing.
    """
    fx, fy, u0, v0 = intrinsics[0], intrinsics[1], intrinsics[2], intrinsics[3]
    height, width = out.shape[1], out.shape[2]
    for b in prange(turns.shape[0]):
        m = turns[b]
        for row in range(height):
            for col in range(width):
                out[b, row, col] = 0.0
        for n in range(points.shape[0]):
            px, py, pz = points[n, 0], points[n, 1], points[n, 2]
            x = m[0, 0] * px + m[0, 1] * py + m[0, 2] * pz + offsets[b, 0]
            y = m[1, 0] * px + m[1, 1] * py + m[1, 2] * pz + offsets[b, 1]
            z = max(m[2, 0] * px + m[2, 1] * py + m[2, 2] * pz + offsets[b, 2], 1.0)
            col = int(np.floor(u0 + fx * x / z + 0.5))
            row = int(np.floor(v0 + fy * y / z + 0.5))
            for r in range(max(row - reach, 0), min(row + reach + 1, height)):
                for c in range(max(col - reach, 0), min(col + reach + 1, width)):
                    out[b, r, c] = 1.0
