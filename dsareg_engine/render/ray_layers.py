"""Where each ray of a view runs inside a closed model: the separate stretches (layers) it crosses, per pixel.

:func:`ray_layers` rasterizes a closed mesh in a view and pairs, per pixel, where the ray enters and leaves the
model (sorted by depth, a winding count: a layer runs from where it becomes non-zero to where it is zero again):
up to ``MAX_LAYERS`` intervals, each with its length (mm) and a per-face value of the two faces bounding it (their
mean). Two layers on one ray are two parts of the model at different depths, with a gap between them.

Used by the hemodynamics' overlap test (:func:`layer_counts`: how many parts of the model a pixel sees), its
unmixing (:func:`ray_stretches`: each stretch's length and middle, to tell whose vessel it is) and by the
bolus simulations (a value per face = when contrast arrives there: each stretch keeps its own time).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit

MAX_HITS = 16
MAX_LAYERS = 6


@njit(cache=True)
def _hits(vertices_view, faces, onset, fx, fy, u0, v0, height, width, depth, sign, when, count):
    for f in range(faces.shape[0]):
        a, b, c = vertices_view[faces[f, 0]], vertices_view[faces[f, 1]], vertices_view[faces[f, 2]]
        if a[2] < 1.0 or b[2] < 1.0 or c[2] < 1.0:
            continue
        ua, va = u0 + fx * a[0] / a[2], v0 + fy * a[1] / a[2]
        ub, vb = u0 + fx * b[0] / b[2], v0 + fy * b[1] / b[2]
        uc, vc = u0 + fx * c[0] / c[2], v0 + fy * c[1] / c[2]
        if (ub - ua) * (vc - va) - (vb - va) * (uc - ua) == 0.0:
            continue
        n0 = (b[1] - a[1]) * (c[2] - a[2]) - (b[2] - a[2]) * (c[1] - a[1])
        n1 = (b[2] - a[2]) * (c[0] - a[0]) - (b[0] - a[0]) * (c[2] - a[2])
        n2 = (b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0])
        plane = n0 * a[0] + n1 * a[1] + n2 * a[2]
        x0, x1 = max(int(np.ceil(min(ua, ub, uc))), 0), min(int(np.floor(max(ua, ub, uc))), width - 1)
        y0, y1 = max(int(np.ceil(min(va, vb, vc))), 0), min(int(np.floor(max(va, vb, vc))), height - 1)
        for y in range(y0, y1 + 1):
            for x in range(x0, x1 + 1):
                w0 = (ub - x) * (vc - y) - (vb - y) * (uc - x)
                w1 = (uc - x) * (va - y) - (vc - y) * (ua - x)
                w2 = (ua - x) * (vb - y) - (va - y) * (ub - x)
                if not ((w0 >= 0 and w1 >= 0 and w2 >= 0) or (w0 <= 0 and w1 <= 0 and w2 <= 0)):
                    continue
                dx, dy = (x - u0) / fx, (y - v0) / fy
                dot = n0 * dx + n1 * dy + n2
                k = count[y, x]
                if dot == 0.0 or k >= depth.shape[2]:
                    continue
                depth[y, x, k] = plane / dot * np.sqrt(dx * dx + dy * dy + 1.0)
                sign[y, x, k] = 1 if dot > 0 else -1
                when[y, x, k] = onset[f]
                count[y, x] = k + 1


@njit(cache=True)
def _pair(depth, sign, when, count, length, layer_onset, middle):
    height, width = count.shape
    for y in range(height):
        for x in range(width):
            n = count[y, x]
            order = np.argsort(depth[y, x, :n])
            winding, layer, start, start_when = 0, 0, 0.0, 0.0
            for i in order:
                before = winding
                winding += sign[y, x, i]
                if before == 0 and winding != 0:
                    start, start_when = depth[y, x, i], when[y, x, i]
                elif before != 0 and winding == 0 and layer < length.shape[2]:
                    length[y, x, layer] = depth[y, x, i] - start
                    layer_onset[y, x, layer] = 0.5 * (start_when + when[y, x, i])
                    middle[y, x, layer] = 0.5 * (start + depth[y, x, i])
                    layer += 1


def _traced(vertices_view, faces, face_value, focal_px, principal_px, size):
    width, height = size
    depth = np.zeros((height, width, MAX_HITS))
    sign = np.zeros((height, width, MAX_HITS), np.int64)
    when = np.zeros((height, width, MAX_HITS))
    count = np.zeros((height, width), np.int64)
    _hits(np.ascontiguousarray(vertices_view, np.float64), np.ascontiguousarray(faces, np.int64),
          np.ascontiguousarray(face_value, np.float64), focal_px[0], focal_px[1], principal_px[0], principal_px[1],
          height, width, depth, sign, when, count)
    length = np.zeros((height, width, MAX_LAYERS))
    value = np.full((height, width, MAX_LAYERS), np.inf)
    middle = np.zeros((height, width, MAX_LAYERS))
    _pair(depth, sign, when, count, length, value, middle)
    return length, value, count, middle


def ray_layers(vertices_view: np.ndarray, faces: np.ndarray, face_onset_s: np.ndarray, focal_px: tuple[float, float],
               principal_px: tuple[float, float], size: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """``(length_mm (H, W, L), value (H, W, L))`` of a closed mesh in view coordinates ``(V, 3)`` mm with a value
    per face ``(F,)``; unused layers have length 0 and value ``inf``. ``size`` is ``(W, H)``."""
    length, value, _, _ = _traced(vertices_view, faces, face_onset_s, focal_px, principal_px, size)
    return length, value


def layer_counts(vertices_view: np.ndarray, faces: np.ndarray, focal_px: tuple[float, float],
                 principal_px: tuple[float, float], size: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """``(layers (H, W) int, covered (H, W) bool)``: how many separate parts of the model each pixel's ray crosses,
    and whether it meets the model at all (the hard silhouette, pixel centres)."""
    stretches = ray_stretches(vertices_view, faces, focal_px, principal_px, size)
    return stretches.layers, stretches.covered


@dataclass(frozen=True)
class RayStretches:
    """Per pixel the separate stretches of the model its ray crosses: ``length_mm`` ``(H, W, L)`` (0 = unused),
    ``middle_mm`` ``(H, W, L)`` (distance from the source to the stretch's middle, along the ray) and ``covered``
    ``(H, W)`` (the ray meets the model: the hard silhouette, pixel centres)."""

    length_mm: np.ndarray
    middle_mm: np.ndarray
    covered: np.ndarray

    @property
    def layers(self) -> np.ndarray:
        """``(H, W)`` int: how many separate parts of the model each ray crosses."""
        return (self.length_mm > 0).sum(axis=2)

    def middles_in_view(self, focal_px: tuple[float, float], principal_px: tuple[float, float]
                        ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(pixel (S,), length_mm (S,), middle (S, 3))`` of every stretch: its pixel (row-major index), its length
        and its middle point in view coordinates (mm): the pixel centre's ray ``(x − u0) / fx, (y − v0) / fy, 1``,
        normalised, times the middle's distance."""
        row, col, layer = np.nonzero(self.length_mm > 0)
        dx, dy = (col - principal_px[0]) / focal_px[0], (row - principal_px[1]) / focal_px[1]
        ray = np.stack([dx, dy, np.ones_like(dx)], axis=1)
        ray /= np.linalg.norm(ray, axis=1, keepdims=True)
        middle = ray * self.middle_mm[row, col, layer][:, None]
        return row * self.covered.shape[1] + col, self.length_mm[row, col, layer], middle


def ray_stretches(vertices_view: np.ndarray, faces: np.ndarray, focal_px: tuple[float, float],
                  principal_px: tuple[float, float], size: tuple[int, int]) -> RayStretches:
    """The stretches of a closed mesh in view coordinates ``(V, 3)`` mm each pixel's ray crosses; ``size`` ``(W, H)``."""
    length, _, count, middle = _traced(vertices_view, faces, np.zeros(len(faces)), focal_px, principal_px, size)
    return RayStretches(length, middle, count > 0)
