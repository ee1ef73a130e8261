"""Automatic initial poses: triangulated position + global rotation search over SO(3).

Used when no initial pose is known (``options.initialization``: ``auto`` without a given
pose, or ``search``). Steps:

1. **Position.** Each view's mask centroid back-projects to a ray from its source; the point
   nearest to both rays (least squares) is where the mesh centre goes.
2. **Rotation.** A near-uniform grid of rotations over all of SO(3) (super-Fibonacci, see
   :mod:`.rotation_grid`; the mesh's own axes, the identity, is scored too) is scored at low
   resolution in every view: area-weighted surface points of the mesh are splatted into a
   ~64-px window around the mask, the translation is re-centred per candidate so the splat's
   centroid meets the mask's centroid in both views (linearized, one Gauss–Newton step), and
   the score is ``1 − cosine similarity`` of the blurred splat and the blurred mask, averaged
   over the views (0 = identical). The best candidates are refined by a local hill-climb.
3. **Starts.** The best *distinct* candidates (rotations ≥ ``distinct_deg`` apart) become the
   multi-start's starts.
4. **All of the model shown?** Each start is placed again by the coverage search's shift
   (:func:`~.coverage_search.coverage_on`); when none has :data:`EXPLAINED` of its model pixels on
   the vessels in every view, the images show part of the model and the partial searches run
   (:mod:`.coverage_search` here, :mod:`.branch_search` in the solver). When some do, but none of those also
   reaches :data:`PARTIAL_RECALL` of the vessels in every view, the images hold more than the model (another
   territory, small branches, background: the masks' centroids and extent do not place the model): the coverage
   search runs with a score that weighs precision (model points on vessels) over recall (:data:`HOLDS_MORE`),
   and its best distinct candidates, hill-climbed on a finer canvas, lead the starts (``search+precise``).

Array shapes: ``B`` candidates, ``N`` surface points, ``(H, W)`` the search window.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, replace

import cv2
import numba
import numpy as np

from ...geometry.rig import Rig, ViewGeometry
from ...mesh import TriangleMesh
from ...render.serial_kernels import KernelPair
from . import search_kernels
from .coverage_search import coverage_on, refine_by_coverage, search_by_coverage
from .rotation_grid import grid_spacing_deg, rotation_grid
from .rotation_refine import distinct, hill_climb, poses_from
from .settings import CENTROID, COVERAGE, SearchSettings
from .window import mask_extent_px, mask_window


@dataclass
class Initialization:
    """Outcome of the search.

    Attributes:
        poses: ``(K, 4, 4)`` mesh_to_world starts, best first.
        scores: ``(K,)`` their scores (0 = perfect overlap, 1 = none).
        method: ``"search"``.
        candidates_scored: rotations scored in all (grid + refinement).
        seconds: wall time.
    """

    poses: np.ndarray
    scores: np.ndarray
    method: str
    candidates_scored: int
    seconds: float
    coverage: dict | None = None
    """The coverage search's best candidate: score and per-view precision / recall (None when it did not run)."""
    branch: dict | None = None
    """The branch search's best part: parts searched, its score and share of the faces (None when it did not run)."""
    fit_faces: np.ndarray | None = None
    """``(F,)`` bool: the part of the model the fit renders (the branch search's matching part), or None: all of it."""
    centroid_score: float = 1.0
    """The centroid search's best score for the whole model."""
    explained: dict | None = None
    """The centroid search's starts placed by coverage: the one with most of its model on vessels, its score and
    per-view precision / recall (what decides whether the partial searches run, see :func:`explains_images`)."""

    @property
    def partial_search_needed(self) -> bool:
        """True unless a whole-model start lies on the vessels in every view (or nothing measured it)."""
        return self.explained is None or not self.explained["model_explained"]

    def metrics(self) -> dict:
        return {
            "coverage": self.coverage,
            "branch": self.branch,
            "explained": self.explained,
            "method": self.method,
            "candidates_scored": int(self.candidates_scored),
            "seconds": round(self.seconds, 3),
            "best_score": round(float(self.scores[0]), 4),
            "runner_up_score": round(float(self.scores[1]), 4) if len(self.scores) > 1 else None,
        }


GIVEN_INITIALIZATION = {"method": "given", "candidates_scored": 0, "seconds": 0.0, "best_score": None, "runner_up_score": None,
                        "coverage": None, "branch": None, "explained": None}
"""``metrics.initialization`` when the starts came from a given pose."""


def resolve_initialization(requested: str, pose_given: bool) -> str:
    """``"given"`` or ``"search"``: ``auto`` searches only when no initial pose was given."""
    if requested == "auto":
        return "given" if pose_given else "search"
    return requested


# ---- position ---------------------------------------------------------------------------


def mask_centroid_px(mask: np.ndarray) -> np.ndarray:
    """``(u, v)`` centroid of a boolean mask ``(H, W)``."""
    rows, cols = np.nonzero(mask)
    return np.array([cols.mean(), rows.mean()])


def pixel_ray_world(view: ViewGeometry, pixel_uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Source position and unit direction (world) of the ray through pixel ``(u, v)``."""
    fx, fy = view.focal_px
    u0, v0 = view.principal_point_px
    direction_view = np.array([(pixel_uv[0] - u0) / fx, (pixel_uv[1] - v0) / fy, 1.0])
    direction = view.world_to_view[:3, :3].T @ direction_view  # orthonormal (det ±1): inverse = transpose
    return view.source_position_world, direction / np.linalg.norm(direction)


def triangulate(rays: list[tuple[np.ndarray, np.ndarray]], fallback: np.ndarray | None = None) -> np.ndarray:
    """Least-squares point nearest to the rays ``[(origin, unit direction)]``, world mm ``(3,)``.

    One ray leaves depth free: the point nearest to ``fallback`` (default: the world origin,
    usually the isocentre) along it is returned.
    """
    if len(rays) == 1:
        origin, direction = rays[0]
        anchor = np.zeros(3) if fallback is None else fallback
        return origin + direction * float((anchor - origin) @ direction)
    normal_matrix, right = np.zeros((3, 3)), np.zeros(3)
    for origin, direction in rays:
        projector = np.eye(3) - np.outer(direction, direction)
        normal_matrix += projector
        right += projector @ origin
    return np.linalg.solve(normal_matrix, right)


def triangulate_mask_centroids(masks: dict[str, np.ndarray], rig: Rig) -> np.ndarray:
    """World point (mm) where the views' mask centroids triangulate."""
    rays = [pixel_ray_world(rig.views[name], mask_centroid_px(mask)) for name, mask in masks.items()]
    return triangulate(rays)


# ---- scoring window per view ------------------------------------------------------------


@dataclass
class _Window:
    """One view's scoring window: its geometry, blurred target ``(H, W)`` float32, its norm, and the
    mask's area centroid ``(u, v)`` in window px."""

    view: ViewGeometry
    target: np.ndarray
    target_norm: float
    centroid_px: np.ndarray


def _window(view: ViewGeometry, mask: np.ndarray, settings: SearchSettings) -> _Window:
    window = mask_window(view, mask, mask_extent_px(mask) * (1.0 + 2.0 * settings.margin), settings.window_px)
    padded = window.coverage
    occupied = (padded > 0.05).astype(np.float32)
    target = np.ascontiguousarray(cv2.GaussianBlur(occupied, (0, 0), settings.blur_px, borderType=cv2.BORDER_CONSTANT))
    rows, cols = np.indices(padded.shape)
    centroid = np.array([(padded * cols).sum(), (padded * rows).sum()]) / padded.sum()
    return _Window(window.view, target, float(np.linalg.norm(target)), centroid)


# ---- splatting and scoring --------------------------------------------------------------


def surface_points(mesh: TriangleMesh, count: int, seed: int = 0) -> np.ndarray:
    """``(count, 3)`` points spread over the surface by area (mesh frame mm)."""
    a, b, c = (mesh.vertices[mesh.faces[:, k]] for k in range(3))
    area = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)
    rng = np.random.default_rng(seed)
    face = rng.choice(len(area), size=count, p=area / area.sum())
    r1, r2 = rng.random(count), rng.random(count)
    flip = r1 + r2 > 1.0
    r1[flip], r2[flip] = 1.0 - r1[flip], 1.0 - r2[flip]
    return a[face] + r1[:, None] * (b[face] - a[face]) + r2[:, None] * (c[face] - a[face])


_SEARCH_KERNELS = {name: KernelPair(getattr(search_kernels, name)) for name in ("mean_pixels", "splat_overlap")}
"""The search kernels and their serial twins (used on a 1-thread budget, see :mod:`...render.serial_kernels`)."""


def _view_placement(window: _Window, rotations: np.ndarray, centres: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Kernel inputs: turns ``(B, 3, 3)``, offsets ``(B, 3)`` in the view frame and ``(fx, fy, u0, v0)``."""
    view = window.view
    turns = np.ascontiguousarray(view.world_to_view[:3, :3] @ rotations)
    offsets = np.ascontiguousarray(centres @ view.world_to_view[:3, :3].T + view.world_to_view[:3, 3])
    return turns, offsets, np.array([*view.focal_px, *view.principal_point_px])


def _search_kernel(name: str):
    """The search kernel ``name`` for this thread budget (after any background compile of it is done)."""
    from ...kernels.compile_lock import wait_for_group

    wait_for_group("search")
    return _SEARCH_KERNELS[name].pick(numba.get_num_threads())


def _mean_pixels(window: _Window, rotations: np.ndarray, centres: np.ndarray, points: np.ndarray) -> np.ndarray:
    """``(B, 2)`` mean projected ``(u, v)`` of centred points ``(N, 3)`` turned by ``(B, 3, 3)``, placed at ``(B, 3)``."""
    out = np.empty((len(rotations), 2))
    _search_kernel("mean_pixels")(points, *_view_placement(window, rotations, centres), out)
    return out


def _overlap(window: _Window, rotations: np.ndarray, centres: np.ndarray, points: np.ndarray) -> np.ndarray:
    """``(B, 2)``: Σ blurred target over the pixels the points hit, and the number of those pixels."""
    out = np.empty((len(rotations), 2))
    _search_kernel("splat_overlap")(points, *_view_placement(window, rotations, centres), window.target, out)
    return out


def _translation_jacobian(windows: list[_Window], centre: np.ndarray) -> np.ndarray:
    """``(2V, 3)`` pixels per mm of moving a point at ``centre`` (world), all views stacked."""
    rows = []
    for window in windows:
        view = window.view
        x, y, z = view.world_to_view[:3, :3] @ centre + view.world_to_view[:3, 3]
        fx, fy = view.focal_px
        rows.append(np.array([[fx / z, 0.0, -fx * x / z**2], [0.0, fy / z, -fy * y / z**2]]) @ view.world_to_view[:3, :3])
    return np.concatenate(rows)


def score_candidates(
    windows: list[_Window], rotations: np.ndarray, centre: np.ndarray, points: np.ndarray, settings: SearchSettings
) -> tuple[np.ndarray, np.ndarray]:
    """Scores ``(B,)`` (0 best) and re-centred positions ``(B, 3)`` of rotations ``(B, 3, 3)``.

    Re-centring moves each candidate so its projected surface points' mean meets the mask's
    centroid in every view (one linearized least-squares step). The score is one minus the
    cosine similarity of the candidate's splat ``S`` (binary) and the blurred mask ``T``,
    ``Σ S·T / (‖S‖ ‖T‖)``, averaged over the views: only the target is blurred, so a
    candidate costs one projection and one scatter per view.
    """
    solve = np.linalg.pinv(_translation_jacobian(windows, centre))
    place = np.repeat(centre[None], len(rotations), axis=0)
    shift = [window.centroid_px - _mean_pixels(window, rotations, place, points) for window in windows]
    place = place + np.concatenate(shift, axis=1) @ solve.T
    similarity = np.zeros(len(rotations))
    for window in windows:
        overlap, count = _overlap(window, rotations, place, points).T
        similarity += overlap / (np.sqrt(np.maximum(count, 1.0)) * window.target_norm)
    return 1.0 - similarity / len(windows), place


def search_initial_poses(
    mesh: TriangleMesh, masks: dict[str, np.ndarray], rig: Rig, count: int, settings: SearchSettings = CENTROID,
    coverage: SearchSettings | None = COVERAGE,
) -> Initialization:
    """``count`` distinct starting poses for ``mesh`` from the views' masks (no pose needed).

    Args:
        masks: ``{view: (H, W) bool}``, non-empty; every view given is used.
        rig: calibrated views (their initial pose is ignored).
    """
    started = time.perf_counter()
    centre = triangulate_mask_centroids(masks, rig)
    windows = [_window(rig.views[name], mask, settings) for name, mask in masks.items()]
    points = np.ascontiguousarray(surface_points(mesh, settings.points) - mesh.centroid)
    grid = np.concatenate([np.eye(3)[None], rotation_grid(settings.rotations)])  # the mesh's own axes first
    scores, _ = score_candidates(windows, grid, centre, points, settings)
    top = distinct(grid, scores, settings.refine_top, 0.75 * grid_spacing_deg(settings.rotations))
    rotations, refined, centres, extra = hill_climb(
        lambda trial: score_candidates(windows, trial, centre, points, settings), grid[top], settings.refine_steps_deg)
    chosen = distinct(rotations, refined, max(count, 2), settings.distinct_deg)
    poses = poses_from(rotations[chosen], centres[chosen], mesh.centroid)
    found = Initialization(poses[:count], refined[chosen], "search", len(grid) + extra, time.perf_counter() - started,
                           centroid_score=float(refined[chosen][0]))
    if coverage is None:
        return found
    placed = coverage_on(mesh, masks, rig, centre, points, rotations[chosen], coverage)
    found.explained = explains_images(placed)
    found.seconds = time.perf_counter() - started
    if not found.partial_search_needed:
        found.explained["images_hold_more"] = images_hold_more(placed[1])
        if found.explained["images_hold_more"]:
            _with_precise_starts(found, mesh, masks, rig, centre, points, count, settings.distinct_deg)
        found.seconds = time.perf_counter() - started
        return found
    return _with_coverage_starts(found, mesh, masks, rig, centre, points, count, settings, coverage, started)


def _with_coverage_starts(found: Initialization, mesh, masks, rig, centre, points, count, settings,
                          coverage: SearchSettings, started: float) -> Initialization:
    """Score the grid by coverage (:mod:`.coverage_search`); when its best candidate explains the vessels
    while leaving part of the model unmatched (:func:`looks_partial`), its distinct best candidates lead the starts."""
    searched = search_by_coverage(mesh, masks, rig, centre, points, max(count, 2), settings.distinct_deg, coverage)
    best = searched.best_detail
    found.coverage = {"best_score": round(float(searched.scores[0]), 4),
                      "precision": [round(float(v), 3) for v in best[:, 0]],
                      "recall": [round(float(v), 3) for v in best[:, 1]]}
    found.candidates_scored += searched.scored
    found.seconds = time.perf_counter() - started
    if not looks_partial(best):
        return found
    found.poses = np.concatenate([searched.poses[:PARTIAL_STARTS], found.poses])[:count + PARTIAL_STARTS]
    found.scores = np.concatenate([searched.scores[:PARTIAL_STARTS], found.scores])[:count + PARTIAL_STARTS]
    found.method = "search+coverage"
    return found


EXPLAINED = 0.9
"""A whole-model start explains the model when, placed by coverage, at least this share of its model pixels lie on or
next to vessels (precision), in every view: the images show all of the model, and the partial searches are skipped.
Measured (the search canvas, 1-px tolerance): fully visible phantom and paper's mesh, true and grey-level masks,
0.98–1.0; early filling 40–45 % of the phantom at 1000×774 px 0.57–0.93 (the view that shows least: ≤ 0.84). The
old gate, the centroid search's cosine score ≥ 0.3, missed partial cases scoring 0.25–0.29 (full ones: 0.15–0.26).
Recall (vessels the start reaches) does not decide: images showing more than the model (a catheter, speckle, another
tree) are no case for the partial searches, which look for the part of the model the images show."""


def explains_images(candidates: tuple[np.ndarray, np.ndarray]) -> dict:
    """From ``(scores (B,), precision / recall (B, V, 2))`` of whole-model starts placed by coverage: the one whose
    worst view has the highest precision, and whether that start explains the model (:data:`EXPLAINED`)."""
    scores, detail = candidates
    worst = detail[:, :, 0].min(axis=1)
    best = int(np.argmax(worst))
    return {"model_explained": bool(worst[best] >= EXPLAINED), "best_score": round(float(scores[best]), 4),
            "precision": [round(float(v), 3) for v in detail[best, :, 0]],
            "recall": [round(float(v), 3) for v in detail[best, :, 1]]}


def images_hold_more(detail: np.ndarray) -> bool:
    """From per-view (precision, recall) ``(B, V, 2)`` of whole-model starts placed by coverage: some start lies on
    the vessels (:data:`EXPLAINED` in every view) but none of those reaches :data:`PARTIAL_RECALL` of the vessels in
    every view. A fully visible model's right start reaches them all (0.98–1.0)."""
    precision, recall = detail[:, :, 0].min(axis=1), detail[:, :, 1].min(axis=1)
    explaining = precision >= EXPLAINED
    return bool(explaining.any() and recall[explaining].max() < PARTIAL_RECALL)


HOLDS_MORE = replace(COVERAGE, beta=0.5)
"""The coverage search when the images hold more than the model: ``F_0.5``, precision weighing 4 times recall."""
HOLDS_MORE_FINE = replace(HOLDS_MORE, window_px=96, refine_steps_deg=(3.0, 1.5, 0.75))
"""... its best candidates hill-climbed again on canvases 96 px instead of 40 (as the branch search's fine pass)."""


def _with_precise_starts(found: Initialization, mesh, masks, rig, centre, points, count: int, distinct_deg: float) -> None:
    """The :data:`HOLDS_MORE` coverage search's :data:`PARTIAL_STARTS` best distinct candidates, refined on
    :data:`HOLDS_MORE_FINE`, in front of ``found``'s starts (``method`` ``search+precise``)."""
    searched = search_by_coverage(mesh, masks, rig, centre, points, PARTIAL_STARTS, distinct_deg, HOLDS_MORE)
    poses, scores = refine_by_coverage(mesh, masks, rig, centre, points, searched.poses, HOLDS_MORE_FINE)
    order = np.argsort(scores, kind="stable")
    found.candidates_scored += searched.scored
    found.poses = np.concatenate([poses[order], found.poses])[:count + PARTIAL_STARTS]
    found.scores = np.concatenate([scores[order], found.scores])[:count + PARTIAL_STARTS]
    found.method = "search+precise"


PARTIAL_STARTS = 4
"""Starts the coverage search adds in front of the centroid search's when the images look partial."""
PARTIAL_PRECISION = 0.8
"""The best coverage candidate looks partial when its precision (model points on vessels) is below this in every view..."""
PARTIAL_RECALL = 0.7
"""... while its recall (vessels the model covers) is at least this in every view."""


def looks_partial(precision_recall: np.ndarray) -> bool:
    """True when ``(V, 2)`` per-view (precision, recall) say: the model explains the vessels and has more."""
    return bool(np.all(precision_recall[:, 0] < PARTIAL_PRECISION) and np.all(precision_recall[:, 1] >= PARTIAL_RECALL))
