"""The starts' bookkeeping: the best start kept, the agreeing ones counted, the runner-up."""

from types import SimpleNamespace

import numpy as np

from dsareg_engine.registration.starts import _keep_best, _runner_up


def _problem_without_loss():
    def loss(*args):
        raise AssertionError("the starts' losses were given: no evaluation")

    vertices = np.random.default_rng(0).normal(scale=20.0, size=(50, 3))
    return SimpleNamespace(mesh=SimpleNamespace(vertices=vertices), radius_mm=20.0, loss=loss)


def test_given_losses_rank_the_starts_without_evaluating_them_again():
    problem = _problem_without_loss()
    poses = np.stack([np.eye(4)] * 3)
    poses[1, 0, 3], poses[2, 1, 3] = 0.5, 3.0  # 0.5 mm and 3 mm from the first
    losses = np.array([0.3, 0.1, 0.2])
    best, agreeing = _keep_best(problem, None, poses, losses)
    assert np.array_equal(best[0], poses[1]) and agreeing == 2  # the 3-mm start does not agree (AGREEMENT_ADD_MM 2)
    assert _runner_up(problem, None, poses, losses) is None  # nothing beyond 0.2 x the 20-mm radius
