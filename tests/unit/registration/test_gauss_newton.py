"""Levenberg–Marquardt on the pose: its normal equations against the solver's loss and autograd, and a fit."""

import numpy as np
import pytest
import torch

from dsareg_engine.metrics import mean_distance_mm
from dsareg_engine.registration import RegistrationOptions
from dsareg_engine.registration.gauss_newton import levenberg_marquardt, normal_equations
from dsareg_engine.registration.optimizers import _run_lbfgs
from dsareg_engine.registration.parameterization import PoseIncrement, random_start_poses
from dsareg_engine.registration.problem import _Problem
from dsareg_engine.registration.schedule import Stage


def _stage(blur_px: float, sigma_px: float = 0.25) -> Stage:
    return Stage("test", 1.0, sigma_px, blur_px, ("ap", "lat"), "gauss_newton", 30, 0.1, True, pose_tolerance=1e-4)


@pytest.fixture(scope="module")
def problem(phantom, synthetic_case):
    rig, masks = synthetic_case(phantom, 200, 0.0, 0.0)
    return _Problem(phantom, masks, rig, RegistrationOptions(), torch.device("cpu"), np.eye(4))


@pytest.mark.parametrize("blur_px", [0.0, 1.0])
@pytest.mark.parametrize("thin_vessel_weighting", [False, True])
def test_normal_equations_match_the_loss_and_its_gradient(phantom, synthetic_case, blur_px, thin_vessel_weighting):
    rig, masks = synthetic_case(phantom, 200, 0.0, 0.0)
    problem = _Problem(phantom, masks, rig, RegistrationOptions(thin_vessel_weighting=thin_vessel_weighting),
                       torch.device("cpu"), np.eye(4))
    stage = _stage(blur_px)
    pose = random_start_poses(np.eye(4), problem.centre, 2, 1.0, 1.0, seed=3)[1]
    loss, gradient, hessian = normal_equations(problem, stage, pose, torch.float64)
    increment = PoseIncrement(pose[None], problem.centre, problem.radius_mm)
    delta = torch.zeros((1, 6), dtype=torch.float64, requires_grad=True)
    reference = problem.loss(increment(delta), stage, torch.float64)
    reference.sum().backward()
    assert loss == pytest.approx(float(reference.detach()), rel=1e-10)
    assert np.allclose(2.0 * gradient, delta.grad[0].numpy(), rtol=1e-4, atol=1e-4 * np.abs(gradient).max())
    assert np.allclose(hessian, hessian.T) and np.all(np.linalg.eigvalsh(hessian) > 0)


def test_levenberg_marquardt_recovers_a_small_offset_in_few_evaluations(problem):
    # masks rendered at the identity; the tracking schedule's two stages: blurred, then sharp
    pose = random_start_poses(np.eye(4), problem.centre, 2, 1.5, 1.5, seed=5)[1]
    assert mean_distance_mm(pose, np.eye(4), problem.mesh.vertices) > 1.0
    reports = []
    for stage, most in ((_stage(1.0), 12), (_stage(0.0, sigma_px=0.1), 20)):
        pose, loss, losses, converged, last_steps = levenberg_marquardt(
            problem, stage, pose, torch.float64, 1e-3, lambda iteration, value: reports.append(value))
        assert converged and last_steps is None and len(losses) <= most and loss == pytest.approx(min(losses))
    assert len(reports) >= 4
    # the same optimum as L-BFGS (the full registration's final fit, tighter tolerance) from there
    sharp = _stage(0.0, sigma_px=0.1)
    lbfgs_stage = Stage(**{**vars(sharp), "optimizer": "lbfgs", "max_iterations": 60})
    increment = PoseIncrement(pose[None], problem.centre, problem.radius_mm)
    delta = torch.zeros((1, 6), dtype=torch.float64, requires_grad=True)
    _run_lbfgs(problem, lbfgs_stage, increment, delta, torch.float64, lambda *args: None)
    reference = increment.poses(delta.detach())[0]
    assert mean_distance_mm(pose, reference, problem.mesh.vertices) < 0.02
    assert mean_distance_mm(pose, np.eye(4), problem.mesh.vertices) < 0.15  # ADD at 200 px


def test_a_stage_stopped_by_its_cap_reports_how_far_its_last_steps_moved(problem):
    """At the cap, the largest of the last three accepted Gauss–Newton steps: large while the pose still travels (1.5
    mm off, four evaluations), tiny where it has settled (from the optimum, a tolerance no step meets: under 0.01 mm); None when
    fewer than three steps were taken."""
    far = random_start_poses(np.eye(4), problem.centre, 2, 1.5, 1.5, seed=5)[1]
    blurred = Stage(**{**vars(_stage(1.0)), "max_iterations": 4})
    _, _, losses, converged, travelling = levenberg_marquardt(problem, blurred, far, torch.float64, 1e-12,
                                                              lambda *args: None)
    assert not converged and len(losses) == 4 and travelling is not None and travelling > 0.05
    sharp = Stage(**{**vars(_stage(0.0, sigma_px=0.1)), "max_iterations": 30})
    settled_pose, _, _, _, _ = levenberg_marquardt(problem, sharp, far, torch.float64, 1e-3, lambda *args: None)
    capped = Stage(**{**vars(sharp), "max_iterations": 6})
    _, _, losses, converged, settled = levenberg_marquardt(problem, capped, settled_pose, torch.float64, 1e-12,
                                                           lambda *args: None)
    assert not converged and len(losses) == 6
    assert settled is not None and settled < 0.01
    short = Stage(**{**vars(sharp), "max_iterations": 2})
    assert levenberg_marquardt(problem, short, far, torch.float64, 1e-12, lambda *args: None)[4] is None
