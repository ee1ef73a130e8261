"""The optimizer loop of one stage, from a zero pose increment: Adam on all starts (stop on a plateau), L-BFGS
(stop on pose change) and Levenberg–Marquardt (:mod:`.gauss_newton`, tracking); each returns a
:class:`_StageOutcome`."""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import torch

from .optim import Adam, lbfgs
from .gauss_newton import levenberg_marquardt
from .schedule import WINDOW_TOLERANCE

ADAM_PATIENCE = 8
LBFGS_POSE_TOLERANCE = 1e-4
"""L-BFGS stops when a step changes every pose component by less than this (mm units)."""


@dataclass
class _StageOutcome:
    iterations: int
    seconds: float
    stopped_by: str  # "tolerance" | "iterations"
    losses: list[float]
    final_loss: float | None = None
    """The one start's loss at the end, when the runner knows it (Gauss–Newton); else it is re-evaluated."""
    last_steps_mm: float | None = None
    """Gauss–Newton stopped by its cap: the largest of its last accepted steps (:data:`.gauss_newton.SETTLED_STEPS`),
    mm units; None otherwise."""


def _run_adam(problem, stage, increment, delta, dtype, report) -> _StageOutcome:
    optimizer = Adam(delta, lr=stage.learning_rate)  # not torch.optim's (:mod:`.optim`)
    losses: list[float] = []
    best, since_best = float("inf"), 0
    start = time.perf_counter()
    stopped_by = "iterations"
    iteration = 0
    for iteration in range(1, stage.max_iterations + 1):
        optimizer.zero_grad()
        per_start = problem.loss(increment(delta), stage, dtype)
        per_start.sum().backward()
        optimizer.step()
        value = float(per_start.detach().min())
        losses.append(value)
        report(stage, iteration, value)
        if stage.plateau_window:
            if _window_plateau(losses, stage.plateau_window):
                stopped_by = "tolerance"
                break
        elif value < best * (1.0 - stage.plateau_tolerance):
            best, since_best = value, 0
        else:
            since_best += 1
            if since_best >= ADAM_PATIENCE:
                stopped_by = "tolerance"
                break
    return _StageOutcome(iteration, time.perf_counter() - start, stopped_by, losses)


def _window_plateau(losses: list[float], window: int) -> bool:
    """True when the mean of the last ``window`` losses is less than WINDOW_TOLERANCE below the mean of the window before."""
    if len(losses) < 2 * window:
        return False
    last, before = np.mean(losses[-window:]), np.mean(losses[-2 * window:-window])
    return bool(last > before * (1.0 - WINDOW_TOLERANCE))


def _run_lbfgs(problem, stage, increment, delta, dtype, report) -> _StageOutcome:
    optimizer = lbfgs(  # torch's, built without importing its compiler (:mod:`.optim`)
        delta, lr=1.0, max_iter=stage.max_iterations, max_eval=stage.max_iterations,
        tolerance_grad=1e-12, tolerance_change=LBFGS_POSE_TOLERANCE if stage.pose_tolerance is None else stage.pose_tolerance,
        history_size=10, line_search_fn="strong_wolfe",
    )
    losses: list[float] = []
    start = time.perf_counter()
    # L-BFGS compares its tolerance with loss and slope values: use the sum of squared
    # errors (the per-pixel mean times the pixel count) so they are of order one.
    first = problem.target(stage.views[0], stage, dtype).target
    pixels = float(first.numel())

    def closure():
        delta.grad = None  # (``optimizer.zero_grad`` would import the compiler)
        mean_loss = problem.loss(increment(delta), stage, dtype).sum()
        (mean_loss * pixels).backward()
        losses.append(float(mean_loss.detach()))
        report(stage, len(losses), losses[-1])
        return mean_loss.detach() * pixels

    optimizer.step(closure)
    evaluations = len(losses)
    stopped_by = "iterations" if evaluations >= stage.max_iterations else "tolerance"
    return _StageOutcome(evaluations, time.perf_counter() - start, stopped_by, losses)


def _run_gauss_newton(problem, stage, increment, delta, dtype, report) -> _StageOutcome:
    start = time.perf_counter()
    pose = increment.poses(delta.detach())[0]
    tolerance = LBFGS_POSE_TOLERANCE if stage.pose_tolerance is None else stage.pose_tolerance
    pose, final_loss, losses, converged, last_steps_mm = levenberg_marquardt(
        problem, stage, pose, dtype, tolerance, lambda iteration, loss: report(stage, iteration, loss))
    with torch.no_grad():
        delta.copy_(torch.as_tensor(increment.delta_of(pose[None])))
    return _StageOutcome(len(losses), time.perf_counter() - start, "tolerance" if converged else "iterations", losses,
                         final_loss, last_steps_mm)


_RUNNERS = {"adam": _run_adam, "lbfgs": _run_lbfgs, "gauss_newton": _run_gauss_newton}
