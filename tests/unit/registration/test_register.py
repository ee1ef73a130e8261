"""Two-view registration on the built-in phantom at small image sizes."""

import numpy as np
import pytest

from dsareg_engine.errors import DsaregInputError
from dsareg_engine.registration import RegistrationOptions
from dsareg_engine.registration.solver import RegistrationCanceled, register


def test_two_view_registration_recovers_a_5deg_5mm_offset(phantom, synthetic_case):
    rig, masks = synthetic_case(phantom, 400, 5.0, 5.0)
    events = []
    result = register(phantom, masks, rig, RegistrationOptions(starts=2, ground_truth_mesh_to_world=np.eye(4).tolist()), progress=events.append)
    truth = result.metrics["ground_truth"]
    assert truth["initial_mtre_mm"] > 4.0
    assert truth["rotation_error_deg"] < 0.1
    assert truth["add_mm"] < 0.1
    assert truth["translation_error_mm"] < 0.1
    assert result.metrics["converged"], result.metrics["reason"]
    assert min(view.dice for view in result.views.values()) > 0.95
    assert events and 0 < events[-1]["fraction"] < 1 and {"stage", "iteration", "loss"} <= set(events[-1])
    data = result.to_dict()
    assert np.allclose(np.asarray(data["views"]["ap"]["mesh_to_view"]), rig.views["ap"].world_to_view @ result.mesh_to_world)
    p = np.asarray(data["views"]["lat"]["projection_matrix"])
    point = np.append(phantom.vertices[0], 1.0)
    projected = p @ point
    assert np.allclose(projected[:2] / projected[2], rig.views["lat"].project((result.mesh_to_world @ point)[None, :3])[0])


def test_sequential_configuration_reports_both_phases(phantom, synthetic_case):
    rig, masks = synthetic_case(phantom, 200, 3.0, 3.0)
    result = register(phantom, masks, rig, RegistrationOptions(configuration="lat_then_ap", starts=1, max_iterations=40))
    stages = list(result.metrics["iterations"])
    assert stages[0].startswith("lat:") and stages[-1].startswith("ap+lat:")
    assert set(result.metrics["seconds"]) >= set(stages) | {"total"}


def test_single_view_registration_runs_on_one_mask(phantom, synthetic_case):
    rig, masks = synthetic_case(phantom, 200, 2.0, 2.0)
    result = register(phantom, {"ap": masks["ap"]}, rig, RegistrationOptions(configuration="ap", starts=1, max_iterations=30))
    assert set(result.views) == {"ap"}


def test_cancel_stops_between_iterations(phantom, synthetic_case):
    rig, masks = synthetic_case(phantom, 200, 2.0, 2.0)
    calls = {"n": 0}

    def should_stop():
        calls["n"] += 1
        return calls["n"] > 3

    with pytest.raises(RegistrationCanceled):
        register(phantom, masks, rig, RegistrationOptions(starts=1), should_stop=should_stop)
    assert calls["n"] == 4


def test_mask_of_wrong_size_is_a_clear_error(phantom, synthetic_case):
    rig, masks = synthetic_case(phantom, 200, 2.0, 2.0)
    masks["lat"] = masks["lat"][:100]
    with pytest.raises(DsaregInputError, match="lat.*200x100"):
        register(phantom, masks, rig)


def test_empty_mask_is_a_clear_error(phantom, synthetic_case):
    rig, masks = synthetic_case(phantom, 200, 2.0, 2.0)
    masks["ap"] = np.zeros_like(masks["ap"])
    with pytest.raises(DsaregInputError, match="empty"):
        register(phantom, masks, rig)


def test_mirrored_detectors_107_degrees_apart(phantom):
    """A .rad-style rig: both detector frames mirrored, planes 107° apart, off-centre principal points."""
    from dsareg_engine.geometry.rig import Rig, rotated_view, view_from_detector_pose
    from dsareg_engine.geometry.pose import make_transform, rotation_about_axis
    from dsareg_engine.registration.parameterization import random_start_poses
    from dsareg_engine.render import Camera, render_hard_silhouette
    import torch

    # Detector 400 mm beyond the isocentre (world origin), source 800 mm before it; rows run along world -z.
    rotation = np.stack([[0.0, 1.0, 0.0], [0.0, 0.0, -1.0], [-1.0, 0.0, 0.0]], axis=1)  # detector axes in world
    spacing = (0.6, 0.6)
    detector_origin = np.array([400.0, -150.0, 140.0])
    detector_to_world = make_transform(rotation, detector_origin)
    source = np.array([-800.0, 10.0, -12.0])
    ap = view_from_detector_pose((480, 440), spacing, detector_to_world, source)
    assert ap.is_mirrored
    lat = rotated_view(ap, 107.0, np.array([0.0, 0.0, 1.0]))
    truth = make_transform(rotation_about_axis([0.3, 1.0, 0.2], 0.4), [4.0, -6.0, 3.0])
    initial = random_start_poses(truth, phantom.centroid, 2, 5.0, 5.0, seed=4)[1]
    rig = Rig({"ap": ap, "lat": lat}, initial)
    assert rig.angle_between_views_deg() == pytest.approx(107.0, abs=1e-6)
    vertices, faces = phantom.torch(torch.float64)
    masks = {
        name: render_hard_silhouette(vertices, faces, torch.as_tensor(view.world_to_view @ truth)[None], Camera.from_view(view))[0].numpy()
        for name, view in rig.views.items()
    }
    assert all(mask.sum() > 500 for mask in masks.values())
    result = register(phantom, masks, rig, RegistrationOptions(starts=2, ground_truth_mesh_to_world=truth.tolist()))
    truth_errors = result.metrics["ground_truth"]
    assert truth_errors["add_mm"] < 0.1, truth_errors
    assert truth_errors["rotation_error_deg"] < 0.1, truth_errors


def test_pure_torch_fallback_registers_without_numba(phantom, synthetic_case, monkeypatch):
    """The path CUDA (or a machine without numba) takes: same result quality, no numba kernels."""
    from dsareg_engine.render import silhouette

    monkeypatch.setattr(silhouette, "_numba", None)
    rig, masks = synthetic_case(phantom, 160, 2.0, 2.0)
    result = register(phantom, masks, rig, RegistrationOptions(starts=1, max_iterations=25, ground_truth_mesh_to_world=np.eye(4).tolist()))
    assert result.metrics["ground_truth"]["add_mm"] < result.metrics["ground_truth"]["initial_mtre_mm"] / 2
    assert min(view.dice for view in result.views.values()) > 0.8


def test_registration_tolerates_simulated_segmentation_errors(phantom, synthetic_case):
    """Masks one pixel too wide, with missing segments, a catheter and speckle: still < 1 mm ADD."""
    from dsareg_engine.simulation.segmentation_errors import corrupt

    rig, masks = synthetic_case(phantom, 400, 5.0, 5.0)
    rng = np.random.default_rng(0)
    noisy = {view: corrupt(mask, "all", rng) for view, mask in masks.items()}
    assert all((noisy[view] != masks[view]).sum() > 0.3 * masks[view].sum() for view in masks)
    # the pose only: no mirror fit (the corrupted masks' Dice is below its trigger; it would not move the pose)
    result = register(phantom, noisy, rig, RegistrationOptions(ground_truth_mesh_to_world=np.eye(4).tolist(),
                                                               mirror_check=False))
    assert result.metrics["ground_truth"]["add_mm"] < 1.0


def test_stage_runner_runs_the_fixed_stage_list_then_the_again_stage(phantom, synthetic_case):
    import torch

    from dsareg_engine.registration import preparation

    rig, masks = synthetic_case(phantom, 160, 3.0, 3.0)
    options = RegistrationOptions(starts=2, max_iterations=30)
    names = [stage.name for stage in preparation._prepare(phantom, masks, rig, options, torch.device("cpu")).stages]
    result = register(phantom, masks, rig, options)
    ran = list(result.metrics["iterations"])
    assert ran[:len(names)] == names and all(name.endswith(":again") for name in ran[len(names):])
    assert len(ran) <= len(names) + 1
    repeated = register(phantom, masks, rig, options)
    assert np.array_equal(repeated.mesh_to_world, result.mesh_to_world)
    assert repeated.metrics["iterations"] == result.metrics["iterations"]
