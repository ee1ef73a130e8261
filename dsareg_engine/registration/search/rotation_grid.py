"""Near-uniform rotation grids over all of SO(3) (for the global initial-pose search).

Super-Fibonacci spirals (Alexa, CVPR 2022): ``n`` unit quaternions

    s = i + 1/2,  r = √(s/n),  R = √(1 − s/n),  α = 2π s/φ,  β = 2π s/ψ
    q_i = (r sin α, r cos α, R sin β, R cos β)

with φ = √2 and ψ the real root of ψ⁴ = ψ + 4 (1.533751…). The points cover the unit
3-sphere evenly (up to ±q, the same rotation), so they cover SO(3) evenly; no two are
nearer than the grid's spacing, about ``(8π² / n)^{1/3}`` radians (4096 → ~15°).
"""

from __future__ import annotations

import numpy as np

_PHI = np.sqrt(2.0)
_PSI = 1.533751168755204288118041


def super_fibonacci_quaternions(count: int) -> np.ndarray:
    """``(count, 4)`` unit quaternions ``(x, y, z, w)`` spread evenly over SO(3)."""
    s = np.arange(count, dtype=np.float64) + 0.5
    r = np.sqrt(s / count)
    big_r = np.sqrt(1.0 - s / count)
    alpha = 2.0 * np.pi * s / _PHI
    beta = 2.0 * np.pi * s / _PSI
    return np.stack([r * np.sin(alpha), r * np.cos(alpha), big_r * np.sin(beta), big_r * np.cos(beta)], axis=1)


def quaternions_to_matrices(quaternions: np.ndarray) -> np.ndarray:
    """``(N, 4)`` unit quaternions ``(x, y, z, w)`` → ``(N, 3, 3)`` rotation matrices."""
    x, y, z, w = (quaternions[:, k] for k in range(4))
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], axis=-1),
        np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], axis=-1),
        np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], axis=-1),
    ], axis=1)


def rotation_grid(count: int) -> np.ndarray:
    """``(count, 3, 3)`` rotations spread evenly over SO(3)."""
    return quaternions_to_matrices(super_fibonacci_quaternions(count))


def grid_spacing_deg(count: int) -> float:
    """Typical angle between neighbouring rotations of a ``count``-point grid (degrees)."""
    return float(np.degrees((8.0 * np.pi**2 / count) ** (1.0 / 3.0)))


def axis_angle_matrices(rotation_vectors: np.ndarray) -> np.ndarray:
    """Rodrigues: ``(N, 3)`` rotation vectors (radians) → ``(N, 3, 3)``."""
    angle = np.linalg.norm(rotation_vectors, axis=1)
    axis = rotation_vectors / np.maximum(angle, 1e-12)[:, None]
    k = np.zeros((len(axis), 3, 3))
    k[:, 0, 1], k[:, 0, 2], k[:, 1, 2] = -axis[:, 2], axis[:, 1], -axis[:, 0]
    k[:, 1, 0], k[:, 2, 0], k[:, 2, 1] = axis[:, 2], -axis[:, 1], axis[:, 0]
    sin, cos = np.sin(angle)[:, None, None], np.cos(angle)[:, None, None]
    return np.eye(3) + sin * k + (1.0 - cos) * (k @ k)


def angles_between_deg(rotations: np.ndarray, rotation: np.ndarray) -> np.ndarray:
    """Angles (degrees) between each of ``rotations`` ``(N, 3, 3)`` and one ``rotation`` ``(3, 3)``."""
    trace = np.einsum("nij,ij->n", rotations, rotation)
    return np.degrees(np.arccos(np.clip((trace - 1.0) / 2.0, -1.0, 1.0)))
