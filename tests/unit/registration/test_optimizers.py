"""The optimizer loops of one stage (:mod:`dsareg_engine.registration.optimizers`): Adam's stopping rules."""

import pytest
import torch

from dsareg_engine.registration.schedule import PLATEAU_TOLERANCE, SWITCH_TOLERANCE, Stage, build_schedule


class _SlowlyImprovingProblem:
    """Stands in for the registration problem: its loss falls by 0.1 % per evaluation, forever."""

    def __init__(self):
        self.evaluations = 0

    def loss(self, poses, stage, dtype):
        self.evaluations += 1
        return poses.sum(-1) * 0.0 + 0.999 ** self.evaluations


@pytest.mark.parametrize("tolerance, stops", [(PLATEAU_TOLERANCE, False), (SWITCH_TOLERANCE, True)])
def test_adam_stops_on_a_plateau_of_the_stage_tolerance(tolerance, stops):
    from dsareg_engine.registration.optimizers import ADAM_PATIENCE, _run_adam

    stage = Stage("ap:1/1", 1.0, 0.5, 0.0, ("ap",), "adam", 60, 0.1, True, plateau_tolerance=tolerance)
    delta = torch.zeros((2, 6), dtype=torch.float64, requires_grad=True)
    outcome = _run_adam(_SlowlyImprovingProblem(), stage, lambda d: d, delta, torch.float64, lambda *args: None)
    if stops:  # 0.1 % per step never adds up to 1 % within the patience window
        assert outcome.stopped_by == "tolerance" and outcome.iterations == ADAM_PATIENCE + 1
    else:  # every step or two beats the best by 0.1 %: runs to the cap
        assert outcome.stopped_by == "iterations" and outcome.iterations == 60


class _JitteringProblem:
    """Stands in for the registration problem: its loss jitters by ±3 % around a level that a new best beats by
    0.2 % every 7 evaluations, as the starts near a minimum do at the coarsest level's 0.8-mm step."""

    def __init__(self):
        self.evaluations = 0

    def loss(self, poses, stage, dtype):
        self.evaluations += 1
        jitter = 0.03 * (1 if self.evaluations % 2 else -1) if self.evaluations % 7 else -0.032
        return poses.sum(-1) * 0.0 + (1.0 + jitter) * 0.998 ** (self.evaluations // 7)


def test_the_coarsest_level_stops_on_a_jittering_plateau():
    from dsareg_engine.registration.optimizers import _run_adam

    coarsest = build_schedule("simultaneous", 512, 300)[0]
    assert coarsest.plateau_window > 0 and coarsest.plateau_tolerance == PLATEAU_TOLERANCE
    delta = torch.zeros((8, 6), dtype=torch.float64, requires_grad=True)
    outcome = _run_adam(_JitteringProblem(), coarsest, lambda d: d, delta, torch.float64, lambda *args: None)
    assert outcome.stopped_by == "tolerance" and outcome.iterations <= 3 * coarsest.plateau_window


class _DescendingProblem:
    def __init__(self):
        self.evaluations = 0

    def loss(self, poses, stage, dtype):
        self.evaluations += 1
        return poses.sum(-1) * 0.0 + 0.99 ** self.evaluations


def test_the_coarsest_level_runs_on_while_the_loss_falls():
    from dsareg_engine.registration.optimizers import _run_adam

    coarsest = Stage(**{**vars(build_schedule("simultaneous", 512, 300)[0]), "max_iterations": 40})
    delta = torch.zeros((8, 6), dtype=torch.float64, requires_grad=True)
    outcome = _run_adam(_DescendingProblem(), coarsest, lambda d: d, delta, torch.float64, lambda *args: None)
    assert outcome.stopped_by == "iterations" and outcome.iterations == 40  # 1 % a step: 4 % a window
