"""The stage runner: the fixed stage list run in order on the live starts (border update, start pruning,
windowing, the optimizer, bookkeeping), then the final stage once more when the border moved or a part was
refitted; and the runners' per-iteration callback (cancellation, animation snapshots, progress events)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import torch

from .optimizers import _RUNNERS, _StageOutcome
from .options import RegistrationOptions
from .parameterization import PoseIncrement
from .partial import explained_faces, refit_faces
from .preparation import _Setup
from .problem import _Problem
from .progress import ProgressPlan
from .schedule import Stage
from .starts import _distinct, _keep_best, _ranking_losses, _runner_up

ProgressCallback = Callable[[dict], None]

BORDER_RECHECK_PX = 0.2
"""A refinement whose end pose moves a view's measured border shift by more than this (px) runs once more."""


class RegistrationCanceled(Exception):
    """Raised when ``should_stop()`` returned True between iterations."""


@dataclass
class _Run:
    """The stage runner's state, carried from stage to stage: the live starts and the kept start's history."""

    poses: np.ndarray
    pose_history: list[np.ndarray]
    frames: list[tuple[str, int, np.ndarray]]
    iterations: dict[str, int] = field(default_factory=dict)
    seconds: dict[str, float] = field(default_factory=dict)
    loss_history: list[tuple[str, list[float]]] = field(default_factory=list)
    starts_agreeing: int = 1
    other: dict | None = None
    """Confidence's runner-up (see :func:`_runner_up`), measured when the batched stages hand over."""
    outcome: _StageOutcome | None = None
    final_loss: float = float("nan")
    partial_checked: bool = False


class _Reporter:
    """The runners' per-iteration callback: cancellation, animation snapshots and progress events.

    :meth:`begin` names the stage and the increment/delta being optimized before a runner starts,
    so every name the callback reads is set before it is called.
    """

    def __init__(self, plan: ProgressPlan, options: RegistrationOptions, progress: ProgressCallback | None,
                 should_stop: Callable[[], bool] | None):
        self.plan, self.options, self.progress, self.should_stop = plan, options, progress, should_stop
        self.stage_index = 0
        self.snapshots: list[tuple[int, np.ndarray]] = []
        self.increment: PoseIncrement | None = None
        self.delta: torch.Tensor | None = None

    def begin(self, stage_index: int, increment: PoseIncrement, delta: torch.Tensor) -> None:
        self.stage_index, self.increment, self.delta, self.snapshots = stage_index, increment, delta, []

    def __call__(self, stage: Stage, iteration: int, loss: float) -> None:
        if self.should_stop is not None and self.should_stop():
            raise RegistrationCanceled("registration canceled")
        if self.options.animation:  # every start's pose at this iteration, for the animation
            self.snapshots.append((iteration, self.increment.poses(self.delta.detach())))
        if self.progress is not None and (iteration % 5 == 0 or iteration == 1):
            fraction = self.plan.fraction(self.stage_index, iteration)
            self.progress({"stage": stage.name, "iteration": iteration, "loss": loss, "fraction": fraction})


def _run_stages(setup: _Setup, options: RegistrationOptions, reporter: _Reporter) -> _Run:
    """Run the stage list in order; then, when the final border re-measurement moved (see
    :func:`_border_moved`), the final stage once more as ``<name>:again``."""
    run = _Run(poses=setup.starts, pose_history=[setup.starts[0]], frames=[("initial", 0, setup.initial)])
    finest_scale = max(stage.scale for stage in setup.stages)
    for index, stage in enumerate(setup.stages):
        _run_stage(setup, run, reporter, options, index, stage, finest_scale)
    last = setup.stages[-1]
    if not setup.tracking and _border_moved(setup.problem, options, last, setup.used_views, run.poses[0]):
        again = Stage(**{**vars(last), "name": f"{last.name}:again"})
        _run_stage(setup, run, reporter, options, len(setup.stages), again, finest_scale)
    if _refit_explained(setup.problem, run.poses[0], setup.used_views):
        explained = Stage(**{**vars(last), "name": f"{last.name}:explained"})
        _run_stage(setup, run, reporter, options, len(setup.stages), explained, finest_scale)
    return run


def _refit_explained(problem: _Problem, pose: np.ndarray, used_views) -> bool:
    """After a part was fitted: when the part holds faces the images do not show at ``pose``, fit the faces they
    do show from now on (:func:`.partial.refit_faces`) and return True."""
    if problem.fit_faces is None:
        return False
    explained = explained_faces(problem.mesh, pose, {name: problem.masks[name] for name in used_views}, problem.rig)
    faces = refit_faces(problem.fit_faces, explained)
    if faces is None:
        return False
    problem.fit_part(faces)
    return True


def _run_stage(setup: _Setup, run: _Run, reporter: _Reporter, options: RegistrationOptions, index: int, stage: Stage,
               finest_scale: float) -> None:
    """One stage on ``run.poses``: border update, start pruning, windowing, the optimizer, bookkeeping.
    ``index`` is the stage's place in ``setup.stages`` (``len(setup.stages)`` for the extra final run)."""
    problem, planned = setup.problem, len(setup.stages)
    problem.windows.clear()
    if stage.add_initial_starts:
        run.poses = np.concatenate([run.poses, setup.starts])
    # Fine stages only, and not in the single-view phase of a sequential configuration: one
    # view's depth is loose there, and a border measured at a wrong magnification costs the
    # two-view stages extra iterations to undo.
    fine = (index > 0 and stage.scale >= 0.5 * finest_scale and set(stage.views) == set(setup.used_views) and index < planned
            and not stage.handover)
    if fine and not (problem.partial or setup.tracking or run.partial_checked):
        # The first fine stage: does a live start explain every vessel with part of the model unmatched?
        run.partial_checked = True
        problem.partial = any(problem.looks_partial(pose, stage.views) for pose in run.poses)
    if options.border_correction and fine:
        problem.update_border_shifts(run.pose_history[-1], stage.views)
    if not stage.all_starts and len(run.poses) > 1:
        # Ranked at the stage's own level, once for both (a hand-over too: ranking its coarse starts at full size, sharp,
        # cost two full-size renders per start and view, up to ~0.2 CPU s with 4 starts on the paper's mesh at 800 px).
        losses = _ranking_losses(problem, stage, run.poses)
        run.other = _runner_up(problem, stage, run.poses, losses)
        run.poses, run.starts_agreeing = _keep_best(problem, stage, run.poses, losses)
    dtype = torch.float64 if (stage.optimizer == "lbfgs" if stage.float64 is None else stage.float64) else torch.float32
    increment = PoseIncrement(run.poses, problem.centre, problem.radius_mm)
    # Fine levels with one start (every tracking stage) evaluate the loss in a window.
    windowed = len(run.poses) == 1 and (setup.tracking or stage.scale >= 0.5 * finest_scale)
    if windowed:
        problem.set_windows(stage, run.poses, dtype)
    delta, outcome = _optimize(problem, stage, increment, dtype, reporter, min(index, planned - 1))
    if windowed and not problem.windows_hold(stage, increment.poses(delta.detach()), dtype):
        # The pose left its window (a large step): redo the stage on the whole image.
        problem.windows.clear()
        delta, outcome = _optimize(problem, stage, increment, dtype, reporter, min(index, planned - 1))
    run.poses, run.outcome = increment.poses(delta.detach()), outcome
    if outcome.final_loss is not None and len(run.poses) == 1:
        per_start = torch.tensor([outcome.final_loss])
    else:
        with torch.no_grad():
            per_start = problem.loss(torch.as_tensor(run.poses), stage, dtype)
    best_index = int(torch.argmin(per_start))
    run.final_loss = float(per_start[best_index])
    run.iterations[stage.name] = outcome.iterations
    run.seconds[stage.name] = round(outcome.seconds, 4)
    run.loss_history.append((stage.name, outcome.losses))
    run.pose_history.append(run.poses[best_index])
    run.frames.extend((stage.name, it, snapshot[best_index]) for it, snapshot in reporter.snapshots)
    if reporter.progress is not None:
        reporter.progress({"stage": stage.name, "iteration": outcome.iterations, "loss": run.final_loss,
                           "fraction": reporter.plan.stage_done(min(index, planned - 1))})
    if index >= planned - 1 and len(run.poses) > 1:
        run.poses, run.starts_agreeing = _keep_best(problem, stage, run.poses)
    elif len(run.poses) > 1 and index + 1 < planned and not setup.stages[index + 1].add_initial_starts:
        # Starts that reached the same pose need not all be carried on: keep the best of each group.
        run.poses, agreeing = _distinct(problem, run.poses, per_start.detach().cpu().numpy())
        run.starts_agreeing = agreeing if len(run.poses) == 1 else run.starts_agreeing


def _optimize(problem: _Problem, stage: Stage, increment: PoseIncrement, dtype: torch.dtype, reporter: _Reporter,
              progress_index: int) -> tuple[torch.Tensor, _StageOutcome]:
    """Run the stage's optimizer from a zero increment; returns the final increment ``(B, 6)`` and the outcome."""
    delta = torch.zeros((len(increment.base), 6), dtype=torch.float64, requires_grad=True)
    reporter.begin(progress_index, increment, delta)
    return delta, _RUNNERS[stage.optimizer](problem, stage, increment, delta, dtype, reporter)


def _border_moved(problem: _Problem, options: RegistrationOptions, stage: Stage, used_views, pose: np.ndarray) -> bool:
    """Re-measure the border shifts at the final pose of a refinement; True when one moved by more
    than BORDER_RECHECK_PX (the stage is then run once more with them). The first measurement is
    taken at the last Adam level's pose: on small images (the phantom at 256 px) that pose can be
    far enough off to measure a border 0.3–0.6 px wrong, which the final fit then keeps."""
    if not (options.border_correction and stage.optimizer != "adam" and set(stage.views) == set(used_views)):
        return False
    before = dict(problem.border_shift_px)
    problem.update_border_shifts(pose, stage.views)
    if max(abs(problem.border_shift_px[name] - before[name]) for name in stage.views) > BORDER_RECHECK_PX:
        return True
    problem.border_shift_px = before  # the fit used these: keep them (and report them)
    return False
