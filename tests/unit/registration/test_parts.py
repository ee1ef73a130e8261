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


def test_two_view_pyramids_end_with_levenberg_marquardt_where_the_jacobian_kernel_runs():
    for configuration in ("simultaneous", "ap_then_lat"):
        lbfgs, lm = build_schedule(configuration, 800, 300), build_schedule(configuration, 800, 300, jacobian=True)
        handover, final = lm[-2:]
        assert lm[:-2] == lbfgs[:-2]  # the Adam levels before the last are untouched; the hand-over takes the last one's place
        assert handover.optimizer == final.optimizer == "gauss_newton" and handover.handover and not final.handover
        assert lbfgs[-2].optimizer == "adam" and handover.scale == lbfgs[-2].scale and handover.name == f"{lbfgs[-2].name}:lm"
        assert handover.blur_px > 0 and not handover.all_starts and not handover.float64
        assert final.name == lbfgs[-1].name and final.scale == 1.0 and final.sigma_px == lbfgs[-1].sigma_px and final.float64
    assert build_schedule("ap", 800, 300, jacobian=True) == build_schedule("ap", 800, 300)  # one view: L-BFGS
    assert build_schedule("simultaneous", 150, 300, jacobian=True)[-1].optimizer == "lbfgs"  # no pyramid: L-BFGS
    single = build_schedule("simultaneous", 512, 300, coarsest_scale=0.4, jacobian=True)  # one Adam level: L-BFGS
    assert [stage.optimizer for stage in single] == ["adam", "lbfgs"]


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
