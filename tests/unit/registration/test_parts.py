"""Pieces of the registration: metrics, parameterization, schedule, options."""

import numpy as np
import pytest
import torch

from dsareg_engine.errors import DsaregInputError
from dsareg_engine.geometry.spec import load_rig
from dsareg_engine.metrics import dice, ground_truth_errors, iou, mean_distance_mm, source_position_error_mm
from dsareg_engine.geometry.pose import make_transform, rotation_about_axis
from dsareg_engine.registration.options import parse_options
from dsareg_engine.registration.parameterization import PoseIncrement, random_start_poses
from dsareg_engine.registration.schedule import (
    INTERMEDIATE_TOLERANCE,
    PLATEAU_TOLERANCE,
    SWITCH_TOLERANCE,
    Stage,
    build_schedule,
    pyramid_scales,
)
from dsareg_engine.registration.targets import thin_vessel_weights


def test_overlap_metrics_by_hand():
    a = np.zeros((4, 4), bool)
    b = np.zeros((4, 4), bool)
    a[0, :3] = True  # 3 pixels
    b[0, 1:] = True  # 3 pixels, 2 shared
    assert dice(a, b) == pytest.approx(2 * 2 / 6)
    assert iou(a, b) == pytest.approx(2 / 4)
    assert dice(np.zeros((2, 2), bool), np.zeros((2, 2), bool)) == 1.0


def test_pose_errors_by_hand():
    points = np.array([[1.0, 0.0, 0.0], [-1.0, 0.0, 0.0]])
    shifted = make_transform(np.eye(3), [0.0, 3.0, 4.0])
    assert mean_distance_mm(shifted, np.eye(4), points) == pytest.approx(5.0)
    # A 90° turn about z maps (±1, 0, 0) to (0, ±1, 0): each point moves √2.
    turned = make_transform(rotation_about_axis([0, 0, 1], np.pi / 2), np.zeros(3))
    assert mean_distance_mm(turned, np.eye(4), points) == pytest.approx(np.sqrt(2))
    rig = load_rig("paper")
    errors = ground_truth_errors(turned, np.eye(4), rig.views, points)
    assert errors["rotation_error_deg"] == pytest.approx(90.0)
    # AP source at (-150, 0, 0): in the turned mesh frame it sits at R^T s = (0, 150, 0).
    assert source_position_error_mm(turned, np.eye(4), rig.views["ap"]) == pytest.approx(150 * np.sqrt(2))
    assert errors["mpd_mm"]["ap"] > 0


def test_increment_rotates_about_the_mesh_centre_and_moves_in_mm():
    centre = np.array([10.0, -5.0, 2.0])
    increment = PoseIncrement(np.eye(4)[None], centre, radius_mm=20.0)
    rotate = increment.poses(torch.tensor([[0.0, 0.0, 20.0 * np.pi / 2, 0.0, 0.0, 0.0]], dtype=torch.float64))[0]
    assert np.allclose(rotate[:3, :3] @ centre + rotate[:3, 3], centre)  # centre stays put
    assert np.allclose(rotate[:3, :3], rotation_about_axis([0, 0, 1], np.pi / 2))
    move = increment.poses(torch.tensor([[0.0, 0.0, 0.0, 1.0, 2.0, 3.0]], dtype=torch.float64))[0]
    assert np.allclose(move[:3, 3], [1.0, 2.0, 3.0])


def test_random_starts_have_the_requested_magnitude():
    centre = np.array([1.0, 2.0, 3.0])
    poses = random_start_poses(np.eye(4), centre, 5, 7.0, 4.0, seed=3)
    assert np.allclose(poses[0], np.eye(4))
    for pose in poses[1:]:
        angle = np.degrees(np.arccos((np.trace(pose[:3, :3]) - 1) / 2))
        assert angle == pytest.approx(7.0)
        assert np.linalg.norm(pose[:3, :3] @ centre + pose[:3, 3] - centre) == pytest.approx(4.0)


def test_schedule_shapes():
    assert pyramid_scales(800) == [0.125, 0.25, 0.5, 1.0]
    assert pyramid_scales(150) == [1.0]
    stages = build_schedule("simultaneous", 800, 300)
    assert stages[0].all_starts and stages[-1].optimizer == "lbfgs" and stages[-1].blur_px == 0
    assert all(stage.views == ("ap", "lat") for stage in stages)
    sequential = build_schedule("ap_then_lat", 800, 300)
    assert sequential[0].views == ("ap",) and sequential[-1].views == ("ap", "lat")
    # The single-view phase hands over at a looser plateau; the two-view phase keeps the strict one.
    assert {stage.plateau_tolerance for stage in sequential if stage.views == ("ap",)} == {SWITCH_TOLERANCE}
    # The first level of each two-view ladder keeps the strict one; the levels between it and L-BFGS only
    # hand a pose on and stop at INTERMEDIATE_TOLERANCE.
    assert [stage.plateau_tolerance for stage in sequential if len(stage.views) == 2][0] == PLATEAU_TOLERANCE
    adam = [stage.plateau_tolerance for stage in stages if stage.optimizer == "adam"]
    assert adam[0] == PLATEAU_TOLERANCE and set(adam[1:]) == {INTERMEDIATE_TOLERANCE}
    assert build_schedule("lat", 400, 100)[-1].views == ("lat",)


def test_options_errors_name_the_field():
    with pytest.raises(DsaregInputError, match="options.configuration"):
        parse_options({"configuration": "sideways"})
    with pytest.raises(DsaregInputError, match="options.bogus"):
        parse_options('{"bogus": 1}')


def test_thin_vessel_weights_favour_thin_branches():
    mask = np.zeros((60, 60), bool)
    mask[10:22, 5:55] = True  # thick vessel, radius ~6
    mask[40:42, 5:55] = True  # thin vessel, radius ~1
    weights = thin_vessel_weights(mask)
    assert weights.mean() == pytest.approx(1.0, rel=1e-5)
    assert weights[41, 30] > 3 * weights[16, 30]


class _SlowlyImprovingProblem:
    """Stands in for the registration problem: its loss falls by 0.1 % per evaluation, forever."""

    def __init__(self):
        self.evaluations = 0

    def loss(self, poses, stage, dtype):
        self.evaluations += 1
        return poses.sum(-1) * 0.0 + 0.999 ** self.evaluations


@pytest.mark.parametrize("tolerance, stops", [(PLATEAU_TOLERANCE, False), (SWITCH_TOLERANCE, True)])
def test_adam_stops_on_a_plateau_of_the_stage_tolerance(tolerance, stops):
    from dsareg_engine.registration.schedule import Stage
    from dsareg_engine.registration.solver import ADAM_PATIENCE, _run_adam

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
    from dsareg_engine.registration.solver import _run_adam

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
    from dsareg_engine.registration.solver import _run_adam

    coarsest = Stage(**{**vars(build_schedule("simultaneous", 512, 300)[0]), "max_iterations": 40})
    delta = torch.zeros((8, 6), dtype=torch.float64, requires_grad=True)
    outcome = _run_adam(_DescendingProblem(), coarsest, lambda d: d, delta, torch.float64, lambda *args: None)
    assert outcome.stopped_by == "iterations" and outcome.iterations == 40  # 1 % a step: 4 % a window


def _tree_of_extent(side_px: int, extent_px: int) -> dict[str, np.ndarray]:
    """Masks whose vessels span ``extent_px``: only their extent sets the ladder, so they are cut to the tree's box
    (``side_px`` is the image's side, passed to the schedule apart)."""
    mask = np.zeros((extent_px + 10, extent_px // 2 + 30), bool)
    mask[5, 20] = mask[4 + extent_px, 19 + extent_px // 2] = True  # the box's corners: the extent is its longer side
    return {"ap": mask, "lat": mask}


@pytest.mark.parametrize("side_px", [512, 1024])
def test_the_coarsest_level_follows_the_vessels_extent_without_a_cliff(side_px):
    """Two px more or less of the tree move the coarsest level's scale by about 1 % (a cliff was 2×, at 192 px)."""
    from dsareg_engine.registration.options import RegistrationOptions
    from dsareg_engine.registration.solver import _ladder_schedule

    coarsest = [_ladder_schedule(RegistrationOptions(), side_px, _tree_of_extent(side_px, extent), ("ap", "lat"), 1.0)[0].scale
                for extent in range(100, side_px - 10, 2)]
    steps = np.array(coarsest[:-1]) / np.array(coarsest[1:])
    assert np.all(steps >= 1.0) and steps.max() < 1.03  # monotone: a larger tree, a coarser level; never a jump
    assert coarsest[-1] == pyramid_scales(side_px)[0]  # a tree filling the image: the image's pyramid


def test_a_tree_filling_the_image_keeps_the_image_pyramid():
    from dsareg_engine.registration.options import RegistrationOptions
    from dsareg_engine.registration.solver import _ladder_schedule

    for extent in (400, 630, 750):  # the paper's mesh spans 631-750 px at 800 px (Table 1)
        stages = _ladder_schedule(RegistrationOptions(), 800, _tree_of_extent(800, extent), ("ap", "lat"), 1.0)
        assert [stage.scale for stage in stages] == [stage.scale for stage in build_schedule("simultaneous", 800, 300)]
