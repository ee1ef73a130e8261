"""Pose candidates scored by how much of the images' vessels the model explains (partial visibility).

The centroid search (:mod:`.initialization`) places each rotation so the model's projected
centre meets the mask's centre. When a run shows only part of the model (an early frame, one
injected branch, a model with a territory the run does not fill) the two centres lie far apart
and every candidate is scored at a wrong position. Here each rotation gets its own position:

1. per view, the model's points are splatted onto a canvas twice the size of a window around
   the mask (``S``: the pixels they hit; ``S⁺``: those grown by 1 px) and cross-correlated (FFT)
   with the mask ``M`` and its 1-px dilation ``M⁺``, for every pixel shift ``s`` up to half the
   window: precision ``P(s) = Σ S(p + s) M⁺(p) / |S|`` (model pixels on or next to vessels) and
   recall ``R(s) = Σ S⁺(p + s) M(p) / |M|`` (vessel pixels the model reaches);
2. each view's shift of best ``F_β(P, R)`` (β = 2), stacked, gives the 3D translation by least
   squares through the views' pixel-per-mm Jacobian (one rigid position explains both views),
   at which ``P`` and ``R`` are read back in both views;
3. the score is ``1 − F_β``, averaged over the views: one-sided, recall weighing β² = 4 times
   precision, so model branches projecting onto background cost little while uncovered vessels
   cost much.

Shapes: ``B`` candidates, ``N`` points, canvases ``(C, C)``.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numba
import numpy as np
import scipy.fft

from ..geometry.rig import ViewGeometry
from ..render.serial_kernels import KernelPair
from . import search_kernels


@dataclass(frozen=True)
class CoverageSettings:
    """Knobs of the coverage search.

    Attributes:
        window_px: side of the scoring window (the canvas is twice as large).
        model_reach: the window's half side covers at least this many projected model RMS radii.
        margin: window margin around the mask's bounding box, as a fraction of its size.
        beta: recall weighs β² times precision in the F-score.
        chunk: candidates scored per FFT batch (memory: chunk × C² floats).
        rotations: size of its SO(3) grid (coarser than the centroid search's: each candidate costs FFTs).
        refine_top: best candidates refined by the hill-climb.
        refine_steps_deg: rotation steps of the hill-climb, one round each.
    """

    window_px: int = 40
    model_reach: float = 1.5
    margin: float = 0.3
    beta: float = 2.0
    chunk: int = 512
    rotations: int = 512
    refine_top: int = 16
    refine_steps_deg: tuple[float, ...] = (12.0, 6.0, 3.0)


@dataclass
class CoverageView:
    """One view's canvas: its geometry, the conjugate spectra of the mask and of its 1-px dilation, the
    mask's pixel count and the largest shift searched (canvas px)."""

    view: ViewGeometry
    mask_spectrum: np.ndarray
    near_spectrum: np.ndarray
    mask_pixels: float
    max_shift_px: int


def coverage_view(view: ViewGeometry, mask: np.ndarray, centre_world: np.ndarray, radius_mm: float,
                  settings: CoverageSettings) -> CoverageView:
    """The canvas of ``view`` for ``mask`` ``(H, W)`` bool, sized for a model of RMS radius ``radius_mm`` at ``centre_world``."""
    rows, cols = np.nonzero(mask)
    extent = max(cols.max() - cols.min(), rows.max() - rows.min()) + 1.0
    depth = float((view.world_to_view[:3, :3] @ centre_world + view.world_to_view[:3, 3])[2])
    radius_px = radius_mm * max(view.focal_px) / max(depth, 1.0)
    side = max(extent * (1.0 + 2.0 * settings.margin), 2.0 * settings.model_reach * radius_px)
    scale = min(1.0, settings.window_px / side)
    level = view.scaled(scale)
    pixel_scale = level.width / view.width
    canvas = 4 * round(side * pixel_scale / 4.0)
    centre = np.array([(cols.max() + cols.min()) / 2.0, (rows.max() + rows.min()) / 2.0])
    corner = np.round(pixel_scale * (centre + 0.5) - 0.5 - canvas / 2.0)
    u0, v0 = level.principal_point_px
    canvas_view = ViewGeometry((canvas, canvas), level.pixel_spacing_mm, level.sid_mm,
                               (u0 - corner[0], v0 - corner[1]), level.world_to_view)
    coverage = cv2.resize(mask.astype(np.float32), level.image_size, interpolation=cv2.INTER_AREA)
    padded = np.zeros((canvas, canvas), np.float32)
    c0, r0 = int(corner[0]), int(corner[1])
    src = coverage[max(r0, 0): r0 + canvas, max(c0, 0): c0 + canvas]
    padded[max(-r0, 0): max(-r0, 0) + src.shape[0], max(-c0, 0): max(-c0, 0) + src.shape[1]] = src
    occupied = (padded > 0.05).astype(np.float32)
    near = cv2.dilate(occupied, np.ones((3, 3), np.uint8))
    return CoverageView(canvas_view, np.conj(scipy.fft.rfft2(occupied)), np.conj(scipy.fft.rfft2(near)),
                        float(occupied.sum()), canvas // 4)


_SPLAT = KernelPair(search_kernels.splat_images)


def _placement(view: ViewGeometry, rotations: np.ndarray, centres: np.ndarray):
    turns = np.ascontiguousarray(view.world_to_view[:3, :3] @ rotations)
    offsets = np.ascontiguousarray(centres @ view.world_to_view[:3, :3].T + view.world_to_view[:3, 3])
    return turns, offsets, np.array([*view.focal_px, *view.principal_point_px])


def _splats(canvas: CoverageView, rotations: np.ndarray, centre: np.ndarray, points: np.ndarray, reach: int) -> np.ndarray:
    size = canvas.view.width
    images = np.empty((len(rotations), size, size), np.float32)
    place = np.repeat(centre[None], len(rotations), axis=0)
    _SPLAT.pick(numba.get_num_threads())(points, *_placement(canvas.view, rotations, place), reach, images)
    return images


def _correlate(images: np.ndarray, spectrum: np.ndarray, shifts: np.ndarray) -> np.ndarray:
    """``Σ_p image(p + s) mask(p)`` for ``s`` over ``shifts`` × ``shifts`` (``(B, K, K)``, index ``[v, u]``)."""
    workers = max(1, numba.get_num_threads())
    size = images.shape[-1]
    overlap = scipy.fft.irfft2(scipy.fft.rfft2(images, workers=workers) * spectrum, s=(size, size), workers=workers)
    return overlap[:, shifts][:, :, shifts]


def _precision_recall(canvas: CoverageView, rotations: np.ndarray, centre: np.ndarray, points: np.ndarray) -> np.ndarray:
    """``(B, K, K, 2)`` precision and recall of every candidate over every shift (see the module)."""
    shifts = np.arange(-canvas.max_shift_px, canvas.max_shift_px + 1) % canvas.view.width
    hits = _splats(canvas, rotations, centre, points, 0)
    precision = _correlate(hits, canvas.near_spectrum, shifts) / np.maximum(hits.sum(axis=(1, 2)), 1.0)[:, None, None]
    recall = _correlate(_splats(canvas, rotations, centre, points, 1), canvas.mask_spectrum, shifts) / max(canvas.mask_pixels, 1.0)
    return np.clip(np.stack([precision, recall], axis=-1), 0.0, 1.0)


def f_score(precision_recall: np.ndarray, beta: float) -> np.ndarray:
    """``F_β`` of ``(..., 2)`` (precision, recall)."""
    precision, recall = precision_recall[..., 0], precision_recall[..., 1]
    return (1 + beta**2) * precision * recall / np.maximum(beta**2 * precision + recall, 1e-9)


def _jacobian(canvases: list[CoverageView], centre: np.ndarray) -> np.ndarray:
    """``(2V, 3)`` canvas pixels per mm of moving a point at ``centre`` (world), views stacked."""
    rows = []
    for canvas in canvases:
        view = canvas.view
        x, y, z = view.world_to_view[:3, :3] @ centre + view.world_to_view[:3, 3]
        fx, fy = view.focal_px
        rows.append(np.array([[fx / z, 0.0, -fx * x / z**2], [0.0, fy / z, -fy * y / z**2]]) @ view.world_to_view[:3, :3])
    return np.concatenate(rows)


def coverage_scores(canvases: list[CoverageView], rotations: np.ndarray, centre: np.ndarray, points: np.ndarray,
                    settings: CoverageSettings) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Scores ``(B,)`` (``1 − F_β``, 0 best), positions ``(B, 3)`` (world mm of the points' origin) and
    per-view ``(precision, recall)`` ``(B, V, 2)`` of rotations ``(B, 3, 3)``."""
    jacobian = _jacobian(canvases, centre)
    solve = np.linalg.pinv(jacobian)
    scores, places, detail = [], [], []
    for first in range(0, len(rotations), settings.chunk):
        chunk = rotations[first: first + settings.chunk]
        rows = np.arange(len(chunk))
        maps = [_precision_recall(canvas, chunk, centre, points) for canvas in canvases]
        moves = []
        for values, canvas in zip(maps, canvases):
            best = f_score(values, settings.beta).reshape(len(chunk), -1).argmax(axis=1)
            v, u = np.unravel_index(best, values.shape[1:3])
            moves.append(-(np.stack([u, v], axis=1) - canvas.max_shift_px))  # the model moves by −s
        translation = np.concatenate(moves, axis=1) @ solve.T
        predicted = translation @ jacobian.T
        read = []
        for k, (values, canvas) in enumerate(zip(maps, canvases)):
            reach = canvas.max_shift_px
            shift = np.clip(-np.round(predicted[:, 2 * k: 2 * k + 2]).astype(int), -reach, reach)
            read.append(values[rows, shift[:, 1] + reach, shift[:, 0] + reach])
        precision_recall = np.stack(read, axis=1)
        scores.append(1.0 - f_score(precision_recall, settings.beta).mean(axis=1))
        places.append(centre + translation)
        detail.append(precision_recall)
    return np.concatenate(scores), np.concatenate(places), np.concatenate(detail)
