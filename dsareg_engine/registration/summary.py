"""The result of one registration: the kept pose, per-view overlaps, convergence, the confidence signals and,
with a known truth, the ground-truth errors."""

from __future__ import annotations

import numpy as np
import torch

from ..geometry.pose import validate_rigid
from ..metrics import dice, ground_truth_errors, iou, mean_distance_mm
from ..render import Camera, render_hard_silhouette
from .confidence import ConfidenceThresholds, assess, outside_fraction, settled
from .optimizers import _StageOutcome
from .options import RegistrationOptions
from .partial import match_fractions
from .preparation import _Setup
from .problem import _Problem
from .result import RegistrationResult, ViewResult
from .search.initialization import GIVEN_INITIALIZATION, Initialization
from .stages import _Run
from .targets import shifted_mask
from .tracking import hold_unmeasured_depth, track_metrics

MIN_CONVERGED_DICE = 0.5


def _summary(setup: _Setup, run: _Run, options: RegistrationOptions, total_seconds: float,
             target_points: np.ndarray | None) -> RegistrationResult:
    """The result: the kept pose, per-view overlaps, and metrics (stages, convergence, confidence, ground truth)."""
    problem, used_views, initial = setup.problem, setup.used_views, setup.initial
    mesh, rig = problem.mesh, problem.rig
    estimate, depth_held_mm = run.poses[0], None
    if setup.tracking and options.single_plane_depth == "previous":  # one plane: its depth held (:mod:`.tracking`)
        estimate, depth_held_mm = hold_unmeasured_depth(estimate, initial, rig, used_views, mesh.vertices.mean(axis=0))
    view_results = _view_results(problem, initial, estimate)
    converged, reason = _convergence(run.outcome, view_results)
    metrics = {
        "loss": run.final_loss,
        "iterations": run.iterations,
        "seconds": {**run.seconds, "total": round(total_seconds, 4)},
        "device": str(problem.device),
        "converged": converged,
        "reason": reason,
        "starts": len(setup.starts),
        "starts_agreeing": run.starts_agreeing,
        "initialization": setup.searched.metrics() if setup.searched is not None else GIVEN_INITIALIZATION,
        "configuration": options.configuration,
    }
    points = mesh.vertices if target_points is None else target_points
    if options.border_correction:
        metrics["border_shift_px"] = {name: round(problem.border_shift_px[name], 4) for name in used_views}
    metrics["confidence"] = _confidence(problem, estimate, view_results, run.other, run.outcome, used_views, setup.searched)
    if setup.tracking:
        metrics.update(track_metrics(initial, estimate, options.reference_mesh_to_world, points, rig, used_views,
                                     depth_held_mm, metrics["confidence"]))
    if len(used_views) == 1:
        metrics["warnings"] = [
            (f"single-view registration ({used_views[0]}): translation along that view's central ray and "
             "out-of-plane rotation are only weakly determined by one silhouette; check the pose with the "
             "other view (its dice is reported when its mask is given) or register with both views")
        ]
    if options.ground_truth_mesh_to_world is not None:
        truth = validate_rigid(options.ground_truth_mesh_to_world, field="options.ground_truth_mesh_to_world", allow_mirror=False)
        metrics["ground_truth"] = ground_truth_errors(estimate, truth, rig.views, mesh.vertices, target_points)
        metrics["ground_truth"]["initial_mtre_mm"] = mean_distance_mm(initial, truth, points)
    return RegistrationResult(estimate, initial, view_results, metrics, run.loss_history, run.pose_history, run.frames)


def _confidence(problem, estimate, views, other, outcome, used_views, searched: Initialization | None) -> dict:
    world = problem.mesh.vertices @ estimate[:3, :3].T + estimate[:3, 3]
    fitted = {  # Dice against the target actually fitted: the mask with its border moved by the correction
        name: dice(views[name].silhouette, shifted_mask(problem.targets[name], problem.border_shift_px[name],
                                                        problem.signed_distance(name)) >= 0.5)
        for name in used_views
    }
    return assess({
        "dice": {name: round(fitted[name], 4) for name in used_views},
        "runner_up": other,
        "border_shift_px": {name: round(problem.border_shift_px[name], 3) for name in used_views},
        "outside_fraction": {name: round(outside_fraction(problem.rig.views[name], world), 4) for name in used_views},
        "stopped_on_tolerance": outcome is not None and outcome.stopped_by == "tolerance",
        "final_step_mm": _final_step_mm(outcome),
        **_match_signals({name: match_fractions(views[name].silhouette, problem.masks[name]) for name in used_views}),
        "partial_loss": problem.partial,
        "part_runner_up": (searched.branch or {}).get("runner_up") if searched is not None else None,
    })


def _final_step_mm(outcome: _StageOutcome | None) -> float | None:
    """A final stage stopped by its cap: the largest of its last Gauss–Newton steps, mm (None: not known)."""
    if outcome is None or outcome.stopped_by == "tolerance" or outcome.last_steps_mm is None:
        return None
    return round(float(outcome.last_steps_mm), 5)


def _match_signals(fractions: dict[str, dict]) -> dict:
    """``unmatched_fraction`` / ``uncovered_fraction`` per view, rounded (see :mod:`.partial`)."""
    return {f"{key}_fraction": {name: round(value[key], 4) for name, value in fractions.items()}
            for key in ("unmatched", "uncovered")}


def _view_results(problem: _Problem, initial: np.ndarray, estimate: np.ndarray) -> dict[str, ViewResult]:
    vertices, faces = problem.mesh_tensors(torch.float64)
    results = {}
    for name, view in problem.rig.views.items():
        if name not in problem.masks:
            continue
        camera = Camera.from_view(view)
        poses = torch.as_tensor(np.stack([view.world_to_view @ initial, view.world_to_view @ estimate]), device=problem.device)
        silhouettes = render_hard_silhouette(vertices, faces, poses, camera).cpu().numpy()
        mesh_to_view = view.world_to_view @ estimate
        mask = problem.masks[name]
        results[name] = ViewResult(
            world_to_view=view.world_to_view,
            mesh_to_view=mesh_to_view,
            projection_matrix=view.intrinsic_matrix @ mesh_to_view[:3],
            dice=dice(silhouettes[1], mask),
            iou=iou(silhouettes[1], mask),
            silhouette=silhouettes[1],
            initial_silhouette=silhouettes[0],
        )
    return results


def _convergence(outcome: _StageOutcome | None, views: dict[str, ViewResult]) -> tuple[bool, str]:
    low = ", ".join(f"{name} {result.dice:.3f}" for name, result in views.items() if result.dice < MIN_CONVERGED_DICE)
    if low:
        return False, f"silhouettes overlap poorly after optimization (dice {low}); the pose is likely wrong"
    if settled(_final_step_mm(outcome)):  # (None unless the cap stopped a Gauss–Newton stage)
        return True, (f"pose settled: the final stage's last steps moved less than "
                      f"{ConfidenceThresholds().settled_step_mm} mm (its iteration limit came first)")
    if outcome is None or outcome.stopped_by != "tolerance":
        return False, "iteration limit reached before the pose stopped changing"
    return True, "pose change below tolerance in the final stage"
