"""The starts and their bookkeeping: the pose search's starts (or None to start from the given pose), the best
start kept, starts that reached the same pose merged, the agreeing ones counted, and confidence's runner-up."""

from __future__ import annotations

import numpy as np
import torch

from ..geometry.rig import Rig
from ..mesh import TriangleMesh
from ..metrics import mean_distance_mm
from ..render import Camera, render_hard_silhouette
from .confidence import ConfidenceThresholds, runner_up, tolerant_f_score
from .options import RegistrationOptions
from .problem import _Problem
from .schedule import Stage
from .search.branch_search import with_branch_starts
from .search.initialization import resolve_initialization, search_initial_poses

AGREEMENT_ADD_MM = 2.0
"""Starts whose pose lies within this ADD of the best one after the batched stages agree."""
SEARCH_MIN_STARTS = 8
"""A pose search hands at least this many distinct starts to the solver (measured on grey-level
phantom cases with no initial pose: 4 starts 60 %, 8 starts 80 %, 12 starts 80 % success)."""
DISTINCT_RADIUS_FRACTION = 0.2
"""A start is a distinct solution (confidence's runner-up) beyond this fraction of the mesh's RMS radius
(and beyond AGREEMENT_ADD_MM): nearer ones are the same answer, not yet refined."""


def _initialize(mesh: TriangleMesh, masks: dict[str, np.ndarray], rig: Rig, options: RegistrationOptions):
    """The searched starts (:class:`~.initialization.Initialization`), or None to use the given pose."""
    pose_given = rig.initial_pose_given or options.initial_mesh_to_world is not None
    if resolve_initialization(options.initialization, pose_given) != "search":
        return None
    visible = {name: mask for name, mask in masks.items()
               if name in rig.views and mask.shape == rig.views[name].image_size[::-1] and mask.any()}
    found = search_initial_poses(mesh, visible, rig, max(options.starts, SEARCH_MIN_STARTS))
    if not found.partial_search_needed:
        return found
    return with_branch_starts(found, mesh, visible, rig)


def _ranking_losses(problem: _Problem, stage: Stage, poses: np.ndarray) -> np.ndarray:
    """``(B,)``: the starts' losses at ``stage`` (float32), which rank them."""
    with torch.no_grad():
        return problem.loss(torch.as_tensor(poses), stage, torch.float32).numpy()


def _keep_best(problem: _Problem, stage: Stage, poses: np.ndarray, losses: np.ndarray | None = None) -> tuple[np.ndarray, int]:
    """Keep the start with the lowest loss at ``stage`` (``losses``: :func:`_ranking_losses`, when already known);
    count the starts that agree with it."""
    losses = _ranking_losses(problem, stage, poses) if losses is None else losses
    best = poses[int(np.argmin(losses))]
    return best[None], _agreeing(problem, poses, best)


def _distinct(problem: _Problem, poses: np.ndarray, losses: np.ndarray) -> tuple[np.ndarray, int]:
    """The poses, best first, less those within AGREEMENT_ADD_MM of a better one; and how many agree with the best."""
    kept: list[np.ndarray] = []
    for index in np.argsort(losses, kind="stable"):
        if all(mean_distance_mm(poses[index], other, problem.mesh.vertices) >= AGREEMENT_ADD_MM for other in kept):
            kept.append(poses[index])
    return np.stack(kept), _agreeing(problem, poses, kept[0])


def _agreeing(problem: _Problem, poses: np.ndarray, best: np.ndarray) -> int:
    """How many of ``poses`` lie within AGREEMENT_ADD_MM (ADD) of ``best``."""
    return int(sum(mean_distance_mm(pose, best, problem.mesh.vertices) < AGREEMENT_ADD_MM for pose in poses))


def _runner_up(problem: _Problem, stage: Stage, poses: np.ndarray, losses: np.ndarray | None = None) -> dict | None:
    """The best start that ended elsewhere and how well it and the best fit, see :mod:`.confidence` (``losses``: as
    :func:`_keep_best`'s)."""
    losses = _ranking_losses(problem, stage, poses) if losses is None else losses
    found = runner_up(poses, losses, problem.mesh.vertices, max(AGREEMENT_ADD_MM, DISTINCT_RADIUS_FRACTION * problem.radius_mm))
    if found is None:
        return None
    index, distance = found
    vertices, faces = problem.mesh_tensors(torch.float64)
    fits = []
    for pose in (poses[int(np.argmin(losses))], poses[index]):
        per_view = []
        for name in stage.views:
            view = problem.rig.views[name]
            mesh_to_view = torch.as_tensor(view.world_to_view @ pose, device=problem.device)[None]
            silhouette = render_hard_silhouette(vertices, faces, mesh_to_view, Camera.from_view(view))[0].cpu().numpy()
            per_view.append(tolerant_f_score(silhouette, problem.masks[name], ConfidenceThresholds().fit_tolerance_px))
        fits.append(float(np.mean(per_view)))
    return {"distance_mm": round(distance, 2), "best_fit": round(fits[0], 4), "fit": round(fits[1], 4)}
