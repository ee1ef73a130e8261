"""Levenberg–Marquardt on the six pose increments, from the silhouettes' per-pixel Jacobians.

The loss is a sum of squared pixel residuals ``r = alpha(δ) − target`` (weighted, per view, a mean
over the level's pixels), so its Gauss–Newton model needs only ``J = ∂alpha/∂δ`` ``(pixels, 6)``:
the 6×6 normal equations ``(JᵀJ + μ·diag JᵀJ) s = −Jᵀr`` are trivial to solve, and the step uses
the curvature L-BFGS has to discover over many evaluations. ``J`` comes from the forward-mode
kernel (:mod:`..render.jacobian`), which costs about as much as one render plus its backward.
Each iteration linearizes about the current pose (δ = 0 there); a step that does not lower the
loss is undone and the damping raised.
"""

from __future__ import annotations

from collections.abc import Callable

import cv2
import numpy as np
import torch

from ..render import SilhouetteSettings
from ..render.jacobian import soft_log_keep_tangents
from .parameterization import PoseIncrement
from .targets import gaussian_kernel

DAMPING_START = 1e-3
"""Initial Marquardt damping μ (relative to diag JᵀJ): near Gauss–Newton, trusted from the first step."""
DAMPING_DOWN = 0.3
DAMPING_UP = 10.0
DAMPING_MIN = 1e-6
SETTLED_STEPS = 3
"""A stage that meets its iteration cap reports the largest of its last this many accepted steps, when each was a
Gauss–Newton step (damping at most ``DAMPING_START``): how far the fit's own model still puts the optimum."""


def normal_equations(problem, stage, pose: np.ndarray, dtype: torch.dtype) -> tuple[float, np.ndarray, np.ndarray]:
    """Loss, ``Jᵀr`` ``(6,)`` and ``JᵀJ`` ``(6, 6)`` of one pose ``(4, 4)`` at ``stage`` (``problem``: a :class:`.problem._Problem`).

    The loss equals ``problem.loss`` at that pose (its gradient is 2·Jᵀr).
    """
    from ..render.jacobian import jacobian_kernel

    sums, n_threads = jacobian_kernel("normal_equations")

    tangents_world = PoseIncrement(pose[None], problem.centre, problem.radius_mm).tangents()[0]  # (6, 4, 4)
    vertices, faces = problem.mesh_tensors(dtype, stage)
    settings = SilhouetteSettings(sigma_px=stage.sigma_px)
    loss, gradient, hessian = 0.0, np.zeros(6), np.zeros((6, 6))
    for name in stage.views:
        world_to_view = problem.rig.views[name].world_to_view
        camera, image, weight, pixels = problem.view_inputs(name, stage, dtype)
        mesh_to_view = torch.as_tensor(world_to_view @ pose, dtype=dtype)[None]
        mesh_to_view_tangents = torch.as_tensor(world_to_view @ tangents_world, dtype=dtype)[None]
        log_keep, log_keep_tangents = soft_log_keep_tangents(vertices, faces, mesh_to_view, mesh_to_view_tangents, camera, settings)
        if stage.blur_px > 0:
            view_loss, view_gradient, view_hessian = _blurred_sums(log_keep[0], log_keep_tangents[0], image, weight, stage.blur_px)
        else:
            view_gradient, view_hessian = np.zeros(6), np.zeros((6, 6))
            no_weight = np.zeros((0, 0), dtype=log_keep.dtype)
            view_loss = sums(log_keep[0], log_keep_tangents[0], image.numpy(),
                             no_weight if weight is None else weight.numpy(), n_threads, view_hessian, view_gradient)
        loss += view_loss / pixels
        gradient += view_gradient / pixels
        hessian += view_hessian / pixels
    return float(loss), gradient, hessian


def _blurred_sums(log_keep: np.ndarray, log_keep_tangents: np.ndarray, image: torch.Tensor, weight, blur_px: float):
    """Sums of a blurred level (blur is linear: blur the render and each Jacobian column). Returns (Σ w r², Jᵀwr, JᵀwJ).

    The blur is :func:`~.targets.gaussian_blur`'s (same kernel, zero padding), by OpenCV: 7 channels.
    """
    keep = np.exp(log_keep)
    kernel = gaussian_kernel(blur_px)
    channels = np.concatenate([(1.0 - keep)[None], np.moveaxis(log_keep_tangents * -keep[..., None], -1, 0)])
    blurred = np.stack([cv2.sepFilter2D(channel, -1, kernel, kernel, borderType=cv2.BORDER_CONSTANT) for channel in channels])
    residual = blurred[0].astype(np.float64) - image.numpy()
    columns = blurred[1:].reshape(blurred.shape[0] - 1, -1).astype(np.float64)
    weighted = residual if weight is None else residual * weight.numpy()
    weighted_columns = columns if weight is None else columns * weight.numpy().reshape(1, -1)
    return float((residual * weighted).sum()), columns @ weighted.reshape(-1), weighted_columns @ columns.T


def levenberg_marquardt(
    problem, stage, pose: np.ndarray, dtype: torch.dtype, pose_tolerance: float, report: Callable[[int, float], None],
) -> tuple[np.ndarray, float, list[float], bool, float | None]:
    """Minimize the stage's loss from ``pose`` ``(4, 4)``; each evaluation is one render with its Jacobian.

    Stops when the next step would change every increment component by less than ``pose_tolerance``
    (mm units; that step is taken) or after ``stage.max_iterations`` evaluations. Returns (pose, its loss
    — before the last, unchecked step if it ended on one —, loss per evaluation, stopped on the tolerance, and at
    the cap the largest of the last ``SETTLED_STEPS`` accepted Gauss–Newton steps in mm units, else None).
    """
    loss, gradient, hessian = normal_equations(problem, stage, pose, dtype)
    losses = [loss]
    report(1, loss)
    damping = DAMPING_START
    recent: list[float] = []  # the last accepted steps' sizes, while each was a Gauss–Newton step
    while len(losses) < stage.max_iterations:
        step = -np.linalg.solve(hessian + damping * np.diag(np.diag(hessian)) + 1e-12 * np.eye(6), gradient)
        candidate = PoseIncrement(pose[None], problem.centre, problem.radius_mm).poses(torch.as_tensor(step[None]))[0]
        if float(np.abs(step).max()) < pose_tolerance:
            # Converged: the model's step is below the tolerance. Taking it unchecked is safe at this
            # size (the quadratic model is exact to first order) and saves an evaluation.
            return candidate, loss, losses, True, None
        candidate_loss, candidate_gradient, candidate_hessian = normal_equations(problem, stage, candidate, dtype)
        losses.append(candidate_loss)
        report(len(losses), candidate_loss)
        if candidate_loss <= loss:
            pose, loss, gradient, hessian = candidate, candidate_loss, candidate_gradient, candidate_hessian
            recent = (recent + [float(np.abs(step).max())])[-SETTLED_STEPS:] if damping <= DAMPING_START else []
            damping = max(damping * DAMPING_DOWN, DAMPING_MIN)
        else:
            damping *= DAMPING_UP
    return pose, loss, losses, False, max(recent) if len(recent) == SETTLED_STEPS else None
