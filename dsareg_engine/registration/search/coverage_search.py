"""Pose candidates scored by how much of the images' vessels the model explains (partial visibility).

The centroid search (:mod:`.initialization`) places each rotation so the model's projected
centre meets the mask's centre. When a run shows only part of the model (an early frame, one
injected branch, a model with a territory the run does not fill) the two centres lie far apart
and every candidate is scored at a wrong position. Here each rotation gets its own position:

1. per view, the model's points are splatted onto a canvas twice the size of a window around
   the mask (``S``: the pixels they hit; ``S⁺``: those grown by 1 px) and cross-correlated (FFT)
   with the mask ``M`` and its 1-px dilation ``M⁺``, for every pixel shift ``s`` up to half the
   window: precision ``P(s) = Σ S(p + s) M⁺(p) / Σ S(p + s) (D(p) + w (1 − D(p)))`` (model pixels on or
   next to vessels, of those on the detector ``D`` and, weighed ``w`` < 1, those past its edge: the field
   of view may cut the model, but hiding a part past the edge must not be free) and recall ``R(s) = Σ S⁺(p + s) M(p) / |M|`` (vessel pixels the
   model reaches);
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

from ...geometry.rig import Rig, ViewGeometry
from ...mesh import TriangleMesh
from ...render.serial_kernels import KernelPair
from ..parameterization import mesh_radius_mm
from . import search_kernels
from .rotation_grid import grid_spacing_deg, rotation_grid
from .rotation_refine import distinct, hill_climb, poses_from
from .settings import COVERAGE, SearchSettings
from .window import mask_extent_px, mask_window


@dataclass
class CoverageView:
    """One view's canvas: its geometry, the conjugate spectra of the mask, of its 1-px dilation and of the
    detector's area (1 on the detector, 0 past its edges), the mask's pixel count and the largest shift
    searched (canvas px)."""

    view: ViewGeometry
    mask_spectrum: np.ndarray
    near_spectrum: np.ndarray
    detector_spectrum: np.ndarray
    mask_pixels: float
    max_shift_px: int


def coverage_view(view: ViewGeometry, mask: np.ndarray, centre_world: np.ndarray, radius_mm: float,
                  settings: SearchSettings) -> CoverageView:
    """The canvas of ``view`` for ``mask`` ``(H, W)`` bool, sized for a model of RMS radius ``radius_mm`` at ``centre_world``."""
    extent = mask_extent_px(mask)
    depth = float((view.world_to_view[:3, :3] @ centre_world + view.world_to_view[:3, 3])[2])
    radius_px = radius_mm * max(view.focal_px) / max(depth, 1.0)
    side = max(extent * (1.0 + 2.0 * settings.margin), 2.0 * settings.model_reach * radius_px)
    window = mask_window(view, mask, side, settings.window_px, multiple=4)
    canvas, (c0, r0), level = window.coverage.shape[0], window.corner_px, window.level
    occupied = (window.coverage > 0.05).astype(np.float32)
    near = cv2.dilate(occupied, np.ones((3, 3), np.uint8))
    detector = np.zeros((canvas, canvas), np.float32)
    detector[max(-r0, 0): max(level.height - r0, 0), max(-c0, 0): max(level.width - c0, 0)] = 1.0
    spectra = [np.conj(scipy.fft.rfft2(image)) for image in (occupied, near, detector)]
    return CoverageView(window.view, *spectra, float(occupied.sum()), canvas // 4)


_SPLAT = KernelPair(search_kernels.splat_images)


def _placement(view: ViewGeometry, rotations: np.ndarray, centres: np.ndarray):
    turns = np.ascontiguousarray(view.world_to_view[:3, :3] @ rotations)
    offsets = np.ascontiguousarray(centres @ view.world_to_view[:3, :3].T + view.world_to_view[:3, 3])
    return turns, offsets, np.array([*view.focal_px, *view.principal_point_px])


def _splats(canvas: CoverageView, rotations: np.ndarray, centre: np.ndarray, points: np.ndarray, reach: int) -> np.ndarray:
    from ...kernels.compile_lock import wait_for_group

    wait_for_group("search")  # the splat belongs to the search group (a background helper may be compiling it)
    size = canvas.view.width
    images = np.empty((len(rotations), size, size), np.float32)
    place = np.repeat(centre[None], len(rotations), axis=0)
    _SPLAT.pick(numba.get_num_threads())(points, *_placement(canvas.view, rotations, place), reach, images)
    return images


def _spectra(images: np.ndarray) -> np.ndarray:
    """``(B, C, C // 2 + 1)`` spectra of splat images ``(B, C, C)`` (one per image, shared by its correlations)."""
    return scipy.fft.rfft2(images, workers=max(1, numba.get_num_threads()))


def _correlate(spectra: np.ndarray, spectrum: np.ndarray, shifts: np.ndarray, size: int) -> np.ndarray:
    """``Σ_p image(p + s) mask(p)`` for ``s`` over ``shifts`` × ``shifts`` (``(B, K, K)``, index ``[v, u]``), the
    ``(size, size)`` images given by their :func:`_spectra`."""
    overlap = scipy.fft.irfft2(spectra * spectrum, s=(size, size), workers=max(1, numba.get_num_threads()))
    return overlap[:, shifts][:, :, shifts]


def _precision_recall(canvas: CoverageView, rotations: np.ndarray, centre: np.ndarray, points: np.ndarray,
                      past_edge_weight: float) -> np.ndarray:
    """``(B, K, K, 2)`` precision and recall of every candidate over every shift (see the module)."""
    size = canvas.view.width
    shifts = np.arange(-canvas.max_shift_px, canvas.max_shift_px + 1) % size
    hits = _splats(canvas, rotations, centre, points, 0)
    hit_spectra = _spectra(hits)
    on_detector = _correlate(hit_spectra, canvas.detector_spectrum, shifts, size)
    past_edge = hits.sum(axis=(1, 2))[:, None, None] - on_detector
    precision = _correlate(hit_spectra, canvas.near_spectrum, shifts, size) / np.maximum(on_detector + past_edge_weight * past_edge, 1.0)
    reached = _spectra(_splats(canvas, rotations, centre, points, 1))
    recall = _correlate(reached, canvas.mask_spectrum, shifts, size) / max(canvas.mask_pixels, 1.0)
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
                    settings: SearchSettings) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Scores ``(B,)`` (``1 − F_β``, 0 best), positions ``(B, 3)`` (world mm of the points' origin) and
    per-view ``(precision, recall)`` ``(B, V, 2)`` of rotations ``(B, 3, 3)``."""
    jacobian = _jacobian(canvases, centre)
    solve = np.linalg.pinv(jacobian)
    scores, places, detail = [], [], []
    for first in range(0, len(rotations), settings.chunk):
        chunk = rotations[first: first + settings.chunk]
        rows = np.arange(len(chunk))
        maps = [_precision_recall(canvas, chunk, centre, points, settings.past_edge_weight) for canvas in canvases]
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


@dataclass
class CoverageCandidates:
    """The coverage search's distinct best candidates: ``poses`` ``(K, 4, 4)`` mesh_to_world, best first,
    ``scores`` ``(K,)`` (``1 − F_β``, 0 best), ``best_detail`` ``(V, 2)`` the best one's per-view (precision,
    recall), ``scored`` rotations scored in all."""

    poses: np.ndarray
    scores: np.ndarray
    best_detail: np.ndarray
    scored: int


def _canvases(mesh: TriangleMesh, masks: dict[str, np.ndarray], rig: Rig, centre: np.ndarray,
              settings: SearchSettings) -> list[CoverageView]:
    """One canvas per view of ``masks``, sized for ``mesh``'s RMS radius at ``centre``."""
    radius = mesh_radius_mm(mesh.vertices)
    return [coverage_view(rig.views[name], mask, centre, radius, settings) for name, mask in masks.items()]


def search_by_coverage(mesh: TriangleMesh, masks: dict[str, np.ndarray], rig: Rig, centre: np.ndarray, points: np.ndarray,
                       count: int, distinct_deg: float, settings: SearchSettings = COVERAGE) -> CoverageCandidates:
    """Grid of ``settings.rotations`` scored by coverage, the best refined by the hill-climb, ``count`` distinct
    (``distinct_deg`` apart) kept. ``centre`` (world mm): where the masks' centroids triangulate; ``points``
    ``(N, 3)``: the mesh's surface points less its centroid."""
    canvases = _canvases(mesh, masks, rig, centre, settings)
    grid = np.concatenate([np.eye(3)[None], rotation_grid(settings.rotations)])
    scores, _, _ = coverage_scores(canvases, grid, centre, points, settings)
    top = distinct(grid, scores, settings.refine_top, 0.75 * grid_spacing_deg(settings.rotations))
    rotations, refined, centres, extra = hill_climb(
        lambda trial: coverage_scores(canvases, trial, centre, points, settings)[:2], grid[top], settings.refine_steps_deg)
    chosen = distinct(rotations, refined, count, distinct_deg)
    _, _, detail = coverage_scores(canvases, rotations[chosen[:1]], centre, points, settings)
    return CoverageCandidates(poses_from(rotations[chosen], centres[chosen], mesh.centroid), refined[chosen], detail[0],
                              len(grid) + extra)


def coverage_on(mesh: TriangleMesh, masks: dict[str, np.ndarray], rig: Rig, centre: np.ndarray, points: np.ndarray,
                rotations: np.ndarray, settings: SearchSettings = COVERAGE) -> tuple[np.ndarray, np.ndarray]:
    """Rotations ``(B, 3, 3)`` each placed by coverage: scores ``(B,)`` and per-view (precision, recall) ``(B, V, 2)``
    (arguments as :func:`search_by_coverage`; no search)."""
    scores, _, detail = coverage_scores(_canvases(mesh, masks, rig, centre, settings), rotations, centre, points, settings)
    return scores, detail


def refine_by_coverage(mesh: TriangleMesh, masks: dict[str, np.ndarray], rig: Rig, centre: np.ndarray, points: np.ndarray,
                       poses: np.ndarray, settings: SearchSettings) -> tuple[np.ndarray, np.ndarray]:
    """Poses ``(K, 4, 4)`` hill-climbed on ``settings``' canvases (e.g. finer ones) from ``poses``' rotations;
    returns the refined poses and their scores ``(K,)`` (arguments as :func:`search_by_coverage`)."""
    canvases = _canvases(mesh, masks, rig, centre, settings)
    rotations, scores, centres, _ = hill_climb(
        lambda trial: coverage_scores(canvases, trial, centre, points, settings)[:2], poses[:, :3, :3], settings.refine_steps_deg)
    return poses_from(rotations, centres, mesh.centroid), scores
