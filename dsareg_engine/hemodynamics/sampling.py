"""Time–density curves of vessel points: each point's projected cross-section as one row of a sparse matrix.

A vessel point (centre ``c``, radius ``r``, mesh mm) projects at ``(u, v)`` px (pixel centres at integers) with
a radius ``r_px = r · f / z`` (``f`` focal length px, ``z`` depth mm). Its **footprint** is the disc of radius
``max(FOOTPRINT_FRACTION · r_px, MIN_FOOTPRINT_PX)`` around ``(u, v)``: the vessel's projected cross-section
there, not one pixel. Its **background** is the ring from ``RING_INNER · r_px + RING_GAP_PX`` to that plus
``RING_WIDTH_PX``, without the pixels the model covers (the model's silhouette at the pose, dilated by one
pixel). A curve is the footprint's mean opacity minus the background ring's, per frame.

All points and all frames at once: ``F`` ``(N, H·W)`` and ``B`` ``(N, H·W)`` (rows sum to 1) times the frame
stack ``(H·W, T)`` give ``(N, T)`` curves in one sparse product.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy import sparse

from ..geometry.rig import ViewGeometry

FOOTPRINT_FRACTION = 0.8
MIN_FOOTPRINT_PX = 1.0
RING_INNER = 1.5
RING_GAP_PX = 2.0
RING_WIDTH_PX = 3.0
MAX_RADIUS_PX = 24.0


@dataclass(frozen=True)
class Projection:
    """Vessel points in one view: ``uv_px`` ``(N, 2)``, ``depth_mm`` ``(N,)``, ``radius_px`` ``(N,)`` (the
    vessel's projected radius) and ``inside`` ``(N,)`` (the footprint lies within the image)."""

    uv_px: np.ndarray
    depth_mm: np.ndarray
    radius_px: np.ndarray
    inside: np.ndarray

    @property
    def footprint_px(self) -> np.ndarray:
        return np.maximum(FOOTPRINT_FRACTION * self.radius_px, MIN_FOOTPRINT_PX)


def project_points(centres_mm: np.ndarray, radii_mm: np.ndarray, view: ViewGeometry, mesh_to_world: np.ndarray
                   ) -> Projection:
    """Project vessel points ``(N, 3)`` mesh mm at the pose ``mesh_to_world`` into ``view``."""
    mesh_to_view = view.world_to_view @ np.asarray(mesh_to_world, float)
    in_view = centres_mm @ mesh_to_view[:3, :3].T + mesh_to_view[:3, 3]
    depth = in_view[:, 2]
    fx, fy = view.focal_px
    u0, v0 = view.principal_point_px
    safe = np.where(depth > 1.0, depth, np.inf)
    uv = np.stack([u0 + fx * in_view[:, 0] / safe, v0 + fy * in_view[:, 1] / safe], axis=1)
    radius = np.minimum(radii_mm * 0.5 * (fx + fy) / safe, MAX_RADIUS_PX)
    margin = np.maximum(FOOTPRINT_FRACTION * radius, MIN_FOOTPRINT_PX)
    inside = (depth > 1.0) & (uv[:, 0] - margin >= -0.5) & (uv[:, 1] - margin >= -0.5) \
        & (uv[:, 0] + margin <= view.width - 0.5) & (uv[:, 1] + margin <= view.height - 0.5)
    return Projection(np.where(np.isfinite(uv), uv, -1e6), depth, np.where(np.isfinite(radius), radius, 0.0), inside)


def _disc_entries(uv: np.ndarray, inner: np.ndarray, outer: np.ndarray, shape: tuple[int, int], reach: int
                  ) -> tuple[np.ndarray, np.ndarray]:
    """``(point, pixel)`` pairs of the pixels with ``inner ≤ distance ≤ outer`` from ``uv``, on a stencil of ``reach``."""
    height, width = shape
    offsets = np.arange(-reach, reach + 1)
    dx, dy = (grid.ravel() for grid in np.meshgrid(offsets, offsets))
    base = np.round(uv).astype(np.int64)
    cols = base[:, :1] + dx[None]
    rows = base[:, 1:] + dy[None]
    distance = np.hypot(cols - uv[:, :1], rows - uv[:, 1:])
    keep = (distance >= inner[:, None]) & (distance <= outer[:, None]) & (cols >= 0) & (cols < width) \
        & (rows >= 0) & (rows < height)
    point, slot = np.nonzero(keep)
    return point, rows[point, slot] * width + cols[point, slot]


def _disc_matrix(uv: np.ndarray, inner: np.ndarray, outer: np.ndarray, shape: tuple[int, int],
                 allowed: np.ndarray | None = None) -> sparse.csr_matrix:
    """Rows of equal weights (summing to 1) over the pixels with ``inner ≤ distance ≤ outer`` from ``uv``;
    ``allowed`` ``(H·W,)`` bool keeps only those pixels. A row with no pixel stays empty. Points are grouped by
    the stencil they need (a few large vessels do not make every point's stencil large)."""
    reach = np.ceil(np.maximum(outer, 1.0)).astype(np.int64)
    points, pixels = [], []
    for size in np.unique(reach):
        group = np.flatnonzero(reach == size)
        point, pixel = _disc_entries(uv[group], inner[group], outer[group], shape, int(size))
        points.append(group[point])
        pixels.append(pixel)
    point, pixel = np.concatenate(points), np.concatenate(pixels)
    if allowed is not None:
        ok = allowed[pixel]
        point, pixel = point[ok], pixel[ok]
    counts = np.bincount(point, minlength=len(uv)).astype(float)
    weights = 1.0 / counts[point]
    return sparse.csr_matrix((weights, (point, pixel)), shape=(len(uv), shape[0] * shape[1]))


@dataclass(frozen=True)
class Footprints:
    """Sampling matrices of one view: ``footprint`` and ``ring`` ``(N, H·W)`` csr, and ``ring_pixels`` ``(N,)``."""

    footprint: sparse.csr_matrix
    ring: sparse.csr_matrix
    footprint_pixels: np.ndarray
    ring_pixels: np.ndarray


def footprints(projection: Projection, silhouette: np.ndarray) -> Footprints:
    """The footprint and background-ring matrices of the projected points; ``silhouette`` ``(H, W)`` bool is the
    model at the pose (the ring avoids it)."""
    shape = silhouette.shape
    rho = projection.footprint_px
    covered = cv2.dilate(silhouette.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool).ravel()
    inner = RING_INNER * projection.radius_px + RING_GAP_PX
    foot = _disc_matrix(projection.uv_px, np.zeros_like(rho), rho, shape)
    ring = _disc_matrix(projection.uv_px, inner, inner + RING_WIDTH_PX, shape, allowed=~covered)
    return Footprints(foot, ring, np.diff(foot.indptr), np.diff(ring.indptr))


def mean_chord_mm(projection: Projection, radii_mm: np.ndarray, samples: int = 33) -> np.ndarray:
    """``(N,)`` the mean X-ray path (mm) through a vessel of radius ``radii_mm`` over its footprint: a cylinder across
    the footprint disc, its axis through the centre. ``2 r`` times the disc-weighted mean of ``√(1 − (x/r)²)``
    (0 where ``|x| > r``): about ``0.8 · 2 r`` when the footprint is ``0.8 r``; less for a thin vessel whose
    footprint (at least ``MIN_FOOTPRINT_PX``) reaches past its walls. What a filled vessel there shows, relative."""
    rho = projection.footprint_px
    x = np.linspace(-1.0, 1.0, samples)[None, :] * rho[:, None]  # across the vessel, px
    weight = np.sqrt(np.maximum(rho[:, None] ** 2 - x ** 2, 0.0))  # the disc's height at x
    radius = np.maximum(projection.radius_px, 1e-6)[:, None]
    chord = np.sqrt(np.maximum(1.0 - (x / radius) ** 2, 0.0))
    fraction = (chord * weight).sum(axis=1) / np.maximum(weight.sum(axis=1), 1e-12)
    return 2.0 * radii_mm * fraction


def curves(stack: np.ndarray, prints: Footprints) -> np.ndarray:
    """``(N, T)`` background-corrected time–density curves from an opacity stack ``(T, H, W)`` (higher = more
    contrast). Points without a background ring keep the footprint's mean alone."""
    flat = stack.reshape(len(stack), -1).T  # (H·W, T)
    inside = prints.footprint @ flat
    background = prints.ring @ flat
    return np.asarray(inside - background, dtype=np.float64)
