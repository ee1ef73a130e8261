"""Pose candidates for a run that fills one part of the model: which branch does it show?

A selective injection fills one branch and what lies downstream of it; a model of two
territories meets a run that injects one. No placement of the *whole* model matches such
images, and the whole-model searches (:mod:`.initialization`, :mod:`.coverage_search`) rank
wrong poses that pile the model onto the vessels above the right one (measured on the paper's
mesh: the true rotation scores 0.17–0.21 by coverage, wrong ones 0.09–0.12). Cut to the part the
run filled, the model matches the images like a fully visible one. So:

1. **Parts.** ``samples`` vertices are drawn (fixed seed) among those farther than
   ``min_distance`` (a fraction of the longest path) from the inflow; each gives its branch and
   everything downstream (:meth:`~dsareg_engine.geometry.vessel_tree.VesselTree.downstream_sets`),
   as the faces whose three vertices are in it, and the rest of the model without it (the filled
   part may hold the inflow, and the inflow is a guess: on a model of two territories joined at
   the inflow it may lie inside the filled one, whose faces are then no branch but the rest of
   the model less the other territory). Parts holding ``min_fraction``–``max_fraction`` of the
   faces are kept — the branches, nearest the inflow first, then the rests — unless they overlap an
   already kept part by more than ``overlap`` (Jaccard), up to ``max_parts``. Before them come the
   **proximal parts**: the faces nearest the inflow along the tree, ``proximal_shares`` of them (an
   early arterial frame fills the tree from its root; no branch or rest is such a part, and on the
   paper's mesh the best of them used to be a rest holding 76–78 % of the faces, or a distal branch
   of 18 %, 1–4 mm off).
2. **Search.** Each part alone, and the whole model, run the coverage search
   (:func:`~.coverage_search.search_by_coverage`, symmetric ``F_1``); each one's best pose is
   hill-climbed again on finer canvases and scored there; that pose places the whole model (a part
   keeps the model's frame). Not the centroid search: it places a candidate by the mean of its
   points, which a part's few faces of a thick stub past the filled vessels pull off (measured:
   a part holding the filled tree and 2 % more faces, a 35 mm stub of the other tree's trunk, was
   placed 12 mm off at its true rotation and scored 0.59 against 0.21 for the filled tree alone,
   so it was never found); the coverage search places each candidate by the shift that best
   overlaps the vessels.
3. **Starts and fit.** When the best part scores below :data:`PART_MATCHES` and beats the whole
   model by :data:`PART_MARGIN`, its pose is the only start and the loss renders that part alone (the pose, the verdict's
   signals and the overlays stay the whole model's): the whole-model candidates, which pile the
   model onto the vessels, would win the loss, and the whole model's unfilled branches pull a fit
   a few mm off (measured on the phantom: a start 2° / 1.9 mm off ended 3.9 mm off). Else the
   parts scoring better than the whole model lead the multi-start (their scores, on the coverage
   scale, stand before the centroid search's in ``scores``), the whole model fitted. A proximal part
   that scores best, below :data:`PART_MATCHES` and below the whole model, is the only start too, but the
   *whole* model is fitted from it (an early frame shows the tree up to a front that no proximal share
   meets exactly; the loss for partial visibility lets the unfilled distal branches lie on background).
   Either way the loss for partial visibility (:mod:`.partial`) is on. When neither any part nor the whole
   model scores below :data:`PART_MATCHES`, nothing of the model is on the images (another patient's tree, AP
   and LAT swapped): the multi-start fit would search every start for a pose that is not there, so the first
   start alone is fitted, for a pose and its verdict (``branch.matches`` false). Before that, the best parts
   get a second look (:func:`second_look`: more of the coarse grid's rotations hill-climbed), for a filled
   branch whose true rotation the coarse pass missed.

Shapes: ``K`` parts, ``V`` vertices, ``F`` faces.
"""

from __future__ import annotations

import hashlib
import time
from dataclasses import dataclass, replace

import numpy as np

from ...geometry.rig import Rig
from ...geometry.vessel_tree import VesselTree, compact, vessel_tree
from ...mesh import TriangleMesh
from ..parameterization import mesh_radius_mm
from .coverage_search import refine_by_coverage, search_by_coverage
from .initialization import Initialization, surface_points, triangulate_mask_centroids
from .settings import COVERAGE, SearchSettings


@dataclass(frozen=True)
class BranchSettings:
    """Knobs of the branch search (see the module).

    Attributes:
        samples: vertices tried as the injection point.
        min_distance: only vertices farther than this fraction of the longest inflow path.
        min_fraction / max_fraction: a part holds this share of the model's faces.
        overlap: a part overlapping a kept one by more than this (Jaccard, faces) is dropped.
        max_parts: branches and rests searched at most (the proximal parts come on top).
        starts: best parts whose poses become starts.
        proximal_shares: proximal parts tried first: the faces nearest the inflow, these shares of them (an early
            arterial frame; see :func:`proximal_parts`).
        coarse: each part's coverage search: its grid, the best ``refine_top`` rotations hill-climbed, on the first
            ``points`` of the part's ``fine.points`` surface points. ``beta`` 1 (both passes): a part's branches off
            the vessels cost as much as vessels it leaves uncovered, so the part that fits the filled vessels
            tightest wins.
        fine: the best pose of each part hill-climbed again on canvases this fine, by these steps, with all ``points``;
            the parts are ranked by that score (on the coarse canvas a part of the model with a third of it past the
            detector's edge scored as well as wrong parts, 0.11–0.16; on the fine one 0.14 against ≥ 0.25, measured
            on the paper's mesh).
    """

    samples: int = 400
    min_distance: float = 0.02
    min_fraction: float = 0.15
    max_fraction: float = 0.85
    overlap: float = 0.85
    max_parts: int = 24
    starts: int = 2
    proximal_shares: tuple[float, ...] = (0.3, 0.4, 0.5, 0.6, 0.75)
    coarse: SearchSettings = replace(COVERAGE, beta=1.0, refine_top=6, points=1000)
    fine: SearchSettings = replace(COVERAGE, beta=1.0, window_px=96, refine_steps_deg=(3.0, 1.5, 0.75), points=2500)
    wide: SearchSettings = replace(COVERAGE, beta=1.0, refine_top=16, points=1000)
    """The second look (:func:`second_look`): the coarse pass with more of its grid's best rotations hill-climbed."""


def proximal_parts(mesh: TriangleMesh, tree: VesselTree, shares: tuple[float, ...]) -> np.ndarray:
    """``(len(shares), F)`` bool: per share, the faces nearest the inflow along the tree (a face's farthest vertex),
    that share of them — the tree as an early arterial frame fills it."""
    face_distance = tree.distances_from(tree.inflow)[mesh.faces].max(axis=1)
    return np.array([face_distance <= np.quantile(face_distance, share) for share in shares], dtype=bool
                    ).reshape(-1, mesh.n_faces)


_PARTS_CACHE: dict[tuple[str, BranchSettings], tuple[np.ndarray, np.ndarray]] = {}
_PARTS_CACHE_SIZE = 4


def candidate_parts(mesh: TriangleMesh, settings: BranchSettings = BranchSettings()) -> tuple[np.ndarray, np.ndarray]:
    """The model's parts to try (see the module, step 1): ``(K, F)`` bool faces, proximal parts first, then the
    branches, then the rests; and ``(K,)`` bool, True for a proximal part. Read-only arrays, remembered per model
    (vertices and faces) across registrations: they depend on the model alone, and one model is registered to
    several runs (measured: 0.5–0.7 CPU s of a 22,000-face model's registration, 0.3 of the paper's mesh)."""
    digest = hashlib.sha1(np.ascontiguousarray(mesh.vertices).tobytes() + np.ascontiguousarray(mesh.faces).tobytes()).hexdigest()
    key = (digest, settings)
    if key not in _PARTS_CACHE:
        if len(_PARTS_CACHE) >= _PARTS_CACHE_SIZE:
            _PARTS_CACHE.pop(next(iter(_PARTS_CACHE)))
        parts, proximal = _candidate_parts(mesh, settings)
        parts.flags.writeable = proximal.flags.writeable = False
        _PARTS_CACHE[key] = parts, proximal
    return _PARTS_CACHE[key]


def _candidate_parts(mesh: TriangleMesh, settings: BranchSettings) -> tuple[np.ndarray, np.ndarray]:
    tree = vessel_tree(mesh)
    from_inflow = tree.distances_from(tree.inflow)
    eligible = np.flatnonzero(from_inflow > settings.min_distance * from_inflow.max())
    rng = np.random.default_rng(0)
    picked = rng.choice(eligible, size=min(settings.samples, len(eligible)), replace=False)
    picked = picked[np.argsort(from_inflow[picked], kind="stable")]
    downstream = tree.downstream_sets(picked)[:, mesh.faces].all(axis=2)
    proximal = proximal_parts(mesh, tree, settings.proximal_shares)
    faces = np.concatenate([proximal, downstream, ~downstream])  # a later part overlapping an earlier one is dropped
    share = faces.mean(axis=1)
    kept: list[int] = []
    for index in np.flatnonzero((share >= settings.min_fraction) & (share <= settings.max_fraction)):
        part = faces[index]
        if all((part & faces[other]).sum() <= settings.overlap * (part | faces[other]).sum() for other in kept):
            kept.append(int(index))
            if sum(other >= len(proximal) for other in kept) == settings.max_parts:
                break
    kept_index = np.array(kept, dtype=int)
    return faces[kept_index].reshape(-1, mesh.n_faces), kept_index < len(proximal)


@dataclass
class BranchCandidates:
    """Per part searched, best first: ``poses`` ``(K, 4, 4)`` mesh_to_world, ``scores`` ``(K,)`` (the coverage
    search's ``1 − F_β``, 0 best), ``faces`` ``(K, F)`` bool, ``fractions`` ``(K,)`` the part's share of the faces,
    ``proximal`` ``(K,)`` bool (a proximal part); ``whole_score`` the whole model's score by the same search;
    ``seconds`` wall."""

    poses: np.ndarray
    scores: np.ndarray
    faces: np.ndarray
    fractions: np.ndarray
    proximal: np.ndarray
    whole_score: float
    seconds: float


def search_parts(mesh: TriangleMesh, masks: dict[str, np.ndarray], rig: Rig, settings: BranchSettings = BranchSettings()
                 ) -> BranchCandidates:
    """Run the coverage search (``F_β``, β = ``settings.fine.beta``) on every candidate part of ``mesh`` and on the
    whole of it (steps 1–2 of the module)."""
    started = time.perf_counter()
    parts, proximal = candidate_parts(mesh, settings)
    centre = triangulate_mask_centroids(masks, rig)
    poses, scores = [], []
    for part in [*parts, np.ones(mesh.n_faces, bool)]:
        pose, score = search_part(mesh, part, masks, rig, centre, settings.coarse, settings.fine)
        poses.append(pose)
        scores.append(score)
    order = np.argsort(scores[:-1], kind="stable")
    return BranchCandidates(np.array(poses[:-1]).reshape(-1, 4, 4)[order], np.array(scores[:-1])[order], parts[order],
                            parts.mean(axis=1)[order], proximal[order], scores[-1], time.perf_counter() - started)


def search_part(mesh: TriangleMesh, faces: np.ndarray, masks: dict[str, np.ndarray], rig: Rig, centre: np.ndarray,
                coarse: SearchSettings, fine: SearchSettings) -> tuple[np.ndarray, float]:
    """The part ``faces`` ``(F,)`` bool of ``mesh`` searched by coverage (``coarse``), its best pose hill-climbed on
    ``fine`` canvases: that pose ``(4, 4)`` (a part keeps the model's frame: it places the whole model) and its score."""
    piece = compact(mesh, faces)
    points = np.ascontiguousarray(surface_points(piece, fine.points) - piece.centroid)
    found = search_by_coverage(piece, masks, rig, centre, points[: coarse.points], 1, 0.0, coarse)
    refined, score = refine_by_coverage(piece, masks, rig, centre, points, found.poses[:1], fine)
    return refined[0], float(score[0])


def second_look(mesh: TriangleMesh, masks: dict[str, np.ndarray], rig: Rig, parts: BranchCandidates,
                settings: BranchSettings = BranchSettings()) -> BranchCandidates:
    """``parts`` with its ``settings.starts`` best searched again by ``settings.wide`` (more of the grid's best
    rotations hill-climbed), a better pose kept, best first again. For when nothing matched: the coarse pass
    hill-climbs only its 6 best rotations, and a small filled branch's true rotation can lie in the basin of the
    grid's 9th (measured: phantom, one branch of 48 %, masks ~100 px across at 512 px: 0.274 and 35° off; from
    16 rotations 0.000, 6° off)."""
    started = time.perf_counter()
    centre = triangulate_mask_centroids(masks, rig)
    poses, scores = parts.poses.copy(), parts.scores.copy()
    for k in range(min(settings.starts, len(scores))):
        pose, score = search_part(mesh, parts.faces[k], masks, rig, centre, settings.wide, settings.fine)
        if score < scores[k]:
            poses[k], scores[k] = pose, score
    order = np.argsort(scores, kind="stable")
    return BranchCandidates(poses[order], scores[order], parts.faces[order], parts.fractions[order],
                            parts.proximal[order], parts.whole_score, parts.seconds + time.perf_counter() - started)


def with_branch_starts(found: Initialization, mesh: TriangleMesh, masks: dict[str, np.ndarray], rig: Rig,
                       settings: BranchSettings = BranchSettings()) -> Initialization:
    """``found`` with the best parts' poses as its only start, or in front of its starts, when they beat the
    whole model by the same coverage score (step 3); ``found.branch`` says what the search saw."""
    parts = search_parts(mesh, masks, rig, settings)
    if len(parts.scores) and min(parts.scores[0], parts.whole_score) >= PART_MATCHES:
        parts = second_look(mesh, masks, rig, parts, settings)
    found.seconds += parts.seconds
    found.branch = {"parts_searched": int(len(parts.scores)), "whole_score": round(parts.whole_score, 4),
                    "best_score": round(float(parts.scores[0]), 4) if len(parts.scores) else None,
                    "faces_fraction": round(float(parts.fractions[0]), 3) if len(parts.scores) else None,
                    "proximal": bool(parts.proximal[0]) if len(parts.scores) else None}
    if not len(parts.scores):
        return found
    best_poses, best_scores = parts.poses[: settings.starts], parts.scores[: settings.starts]
    proximal_leads = parts.proximal[0] and best_scores[0] < min(parts.whole_score, PART_MATCHES)
    if proximal_leads or best_scores[0] < min(parts.whole_score - PART_MARGIN, PART_MATCHES):
        found.branch["matches"] = True
        found.poses, found.scores, found.method = best_poses[:1], best_scores[:1], "search+branch"
        found.fit_faces = None if proximal_leads else parts.faces[0]  # an early frame: the whole model is fitted
        found.branch["runner_up"] = part_runner_up(mesh, parts)
        return found
    better = best_scores < parts.whole_score
    if better.any():
        found.poses = np.concatenate([best_poses[better], found.poses])
        found.scores = np.concatenate([best_scores[better], found.scores])
        found.method = f"{found.method}+branch"
    found.branch["matches"] = bool(min(best_scores[0], parts.whole_score) < PART_MATCHES)
    if not found.branch["matches"]:  # no part of the model is on the images: one fit, for the pose and its verdict
        found.poses, found.scores = found.poses[:1], found.scores[:1]
    return found


def part_runner_up(mesh: TriangleMesh, parts: BranchCandidates) -> dict | None:
    """The best other part scoring within :data:`PART_AMBIGUOUS` of the best one and placing the model elsewhere
    (mean vertex distance above 20 % of its RMS radius and 2 mm): ``{"score", "distance_mm"}``, or None. Only one
    part's pose is fitted, so such a part is an alternative the fit never weighed: the pose is uncertain."""
    distinct_mm = max(2.0, 0.2 * mesh_radius_mm(mesh.vertices))
    best = mesh.vertices @ parts.poses[0][:3, :3].T + parts.poses[0][:3, 3]
    for pose, score in zip(parts.poses[1:], parts.scores[1:]):
        if score - parts.scores[0] > PART_AMBIGUOUS:
            return None
        distance = float(np.linalg.norm(mesh.vertices @ pose[:3, :3].T + pose[:3, 3] - best, axis=1).mean())
        if distance > distinct_mm:
            return {"score": round(float(score), 4), "distance_mm": round(distance, 2)}
    return None


PART_MATCHES = 0.2
"""A part whose fine coverage score (``1 − F_1``) is below this matches the images as a fully visible model does.
Measured (512 px, clinical rig; docs/benchmarks/partial.md): the filled part 0.03–0.14 (0.14 with a third of the
model past the detector's edge), the next best part 0.25–0.34, the whole model 0.31–0.41. The whole-model
searches' candidates then lose to wrong poses in the loss, so the matching part's pose is the only start. When no
part and not the whole model scores below it, nothing of the model is on the images (measured: another vessel tree's
best part 0.16–0.35, AP and LAT swapped 0.24–0.53): the solver fits the first start alone. Another tree's proximal
part can score under it (0.16 / 0.19, 2 of 6 cases on the paper's mesh): such a case is fitted as early filling and
the verdict, not this score, reads it ``failed``."""
PART_MARGIN = 0.05
"""... and beats the whole model's score by this much (measured: 0.09–0.49 where a part was filled; 0.005–0.008
on early filling, where a part holding the filled proximal tree scores like the whole model and the whole
model's fit is the better one)."""
PART_AMBIGUOUS = 0.02
"""A part scoring within this of the leading one while placing the model elsewhere makes the pose uncertain (measured:
a phantom reflux case whose leading part was a wrong one, 4.2 mm off, 0.133 against 0.135 for the next)."""
