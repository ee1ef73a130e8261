"""Tracking mode: re-registration from the previous pose after a small motion (engine and CLI)."""

import json

import numpy as np
import pytest

from dsareg_engine.cli import main
from dsareg_engine.geometry.rig import Rig
from dsareg_engine.geometry.file import save_rig
from dsareg_engine.geometry.pose_file import save_pose
from dsareg_engine.registration import RegistrationOptions
from dsareg_engine.registration.solver import register
from dsareg_engine.registration.parameterization import random_start_poses
from dsareg_engine.registration.track import build_track_schedule, motion_between, track_scale


def test_track_schedule_and_motion():
    assert track_scale(800) == 0.25 and track_scale(400) == 0.5 and track_scale(128) == 1.0
    stages = build_track_schedule(("ap", "lat"), 800, 300)
    assert [stage.optimizer for stage in stages] == ["gauss_newton", "gauss_newton"]
    assert stages[0].scale == 0.25 and stages[0].blur_px > 0 and stages[-1].scale == 1.0 and stages[-1].blur_px == 0
    assert stages[0].level_of_detail and not stages[-1].level_of_detail  # the final fit renders the full mesh
    small = build_track_schedule(("ap", "lat"), 128, 300)  # no smaller level: the blurred stage runs at full size
    assert [(stage.optimizer, stage.scale, stage.blur_px > 0) for stage in small] == [
        ("gauss_newton", 1.0, True), ("gauss_newton", 1.0, False)]
    # without the Jacobian kernel (CUDA): Adam, then L-BFGS
    assert [stage.optimizer for stage in build_track_schedule(("ap", "lat"), 800, 300, jacobian=False)] == ["adam", "lbfgs"]
    points = np.random.default_rng(0).normal(size=(50, 3)) * 10 + 5
    previous = random_start_poses(np.eye(4), points.mean(axis=0), 2, 10.0, 4.0, seed=1)[1]
    step = random_start_poses(np.eye(4), previous[:3, :3] @ points.mean(axis=0) + previous[:3, 3], 2, 2.5, 1.5, seed=2)[1]
    motion = motion_between(previous, step @ previous, points)
    assert motion["rotation_deg"] == pytest.approx(2.5)
    assert motion["translation_mm"] == pytest.approx(1.5)
    assert np.allclose(motion["world_motion"], step)


def _moved_case(mesh, synthetic_case, size):
    rig, _ = synthetic_case(mesh, size, 0.0, 0.0)
    previous = random_start_poses(np.eye(4), mesh.centroid, 2, 1.0, 1.0, seed=4)[1]  # last frame's pose
    truth = random_start_poses(previous, mesh.centroid, 2, 2.0, 2.5, seed=6)[1]  # moved 2° / 2.5 mm since
    import torch

    from dsareg_engine.render import Camera, render_hard_silhouette

    vertices, faces = mesh.torch(torch.float64)
    masks = {name: render_hard_silhouette(vertices, faces, torch.as_tensor(view.world_to_view @ truth)[None],
                                          Camera.from_view(view))[0].numpy() for name, view in rig.views.items()}
    return rig, masks, previous, truth


def test_track_mode_follows_a_small_motion(phantom, synthetic_case):
    rig, masks, previous, truth = _moved_case(phantom, synthetic_case, 400)
    options = RegistrationOptions(mode="track", starts=4, initial_mesh_to_world=previous.tolist(),
                                  ground_truth_mesh_to_world=truth.tolist())
    result = register(phantom, masks, rig, options)
    metrics = result.metrics
    assert metrics["mode"] == "track" and metrics["starts"] == 1  # one start whatever options.starts says
    assert list(metrics["iterations"]) == ["track:ap+lat:1/2", "track:ap+lat:1/1:refine"]
    assert metrics["ground_truth"]["initial_mtre_mm"] > 2.0
    assert metrics["ground_truth"]["add_mm"] < 0.05, metrics["ground_truth"]
    assert metrics["converged"], metrics["reason"]
    expected = motion_between(previous, truth, phantom.vertices)
    assert metrics["motion"]["rotation_deg"] == pytest.approx(expected["rotation_deg"], abs=0.05)
    assert metrics["motion"]["translation_mm"] == pytest.approx(expected["translation_mm"], abs=0.05)


def test_cli_track_from_a_previous_result(phantom, synthetic_case, tmp_path, capsys):
    import cv2

    rig, masks, previous, truth = _moved_case(phantom, synthetic_case, 240)
    phantom.save(tmp_path / "mesh.ply")
    save_rig(Rig(rig.views, np.eye(4)), tmp_path / "geometry.json")
    for name, mask in masks.items():
        cv2.imwrite(str(tmp_path / f"{name}.png"), mask.astype(np.uint8) * 255)
    (tmp_path / "previous").mkdir()  # the pose of a previous result (not a whole result.json: the contract sweep reads those)
    (tmp_path / "previous" / "pose.json").write_text(json.dumps({"mesh_to_world": previous.tolist(), "metrics": {}}))
    save_pose(tmp_path / "truth.json", truth)
    common = ["register", "--mesh", str(tmp_path / "mesh.ply"), "--ap", str(tmp_path / "ap.png"), "--lat", str(tmp_path / "lat.png"),
              "--geometry", str(tmp_path / "geometry.json")]
    assert main([*common, "--track", "--out", str(tmp_path / "x")]) == 2  # --track needs --initial
    assert "--initial" in capsys.readouterr().err
    code = main([*common, "--initial", str(tmp_path / "previous" / "pose.json"), "--track",
                 "--ground-truth", str(tmp_path / "truth.json"), "--out", str(tmp_path / "next")])
    assert code == 0
    assert "motion since --initial" in capsys.readouterr().out
    result = json.loads((tmp_path / "next" / "result.json").read_text())
    assert result["metrics"]["mode"] == "track"
    assert np.allclose(result["initial_mesh_to_world"], previous)
    assert result["metrics"]["ground_truth"]["add_mm"] < 0.1
    assert result["metrics"]["motion"]["translation_mm"] > 1.0


def test_auto_device_tracks_on_the_cpu_where_cuda_would_do_the_full_registration(monkeypatch):
    """Tracking's Levenberg–Marquardt runs on the CPU kernels (faster than CUDA's Adam + L-BFGS there)."""
    import torch

    from dsareg_engine.registration import solver

    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    assert solver._resolve_device("auto", "track").type == "cpu"
    assert solver._resolve_device("auto", "full").type == "cuda"
    assert solver._resolve_device("cuda", "track").type == "cuda"
