"""Runs acquired minutes apart with the head moved between them: a pose per run, the motion, never ``ok``."""

import io

import numpy as np
import pydicom
import pytest
import torch
import trimesh

from dsareg_engine.geometry.pose import make_transform, rotation_about_axis
from dsareg_engine.io.case import load_case
from dsareg_engine.io.dicom_xa import view_from_angles
from dsareg_engine.metrics import mean_distance_mm
from dsareg_engine.pipeline import run_registration_case
from dsareg_engine.registration import RegistrationOptions
from dsareg_engine.registration.motion import held_depth
from dsareg_engine.render import Camera, render_hard_silhouette
from dsareg_engine.simulation.phantom import make_vessel_phantom
from tests.support.result_contract import assert_result_contract

PX, SPACING_MM = 128, 0.9
ANGLES = {"ap": (4.0, 3.0), "lat": (88.0, -2.0)}


def _views():
    return {name: view_from_angles(*ANGLES[name], 1100.0, 760.0, (SPACING_MM, SPACING_MM), (PX, PX)) for name in ANGLES}


def _xa(build, mask: np.ndarray, name: str, time: str) -> bytes:
    pixels = np.where(mask, 900, 3100).astype(np.uint16)  # vessels dark, as in DSA
    dataset = pydicom.dcmread(io.BytesIO(build.xa(pixels, primary=ANGLES[name][0], secondary=ANGLES[name][1],
                                                  sid=1100.0, sod=760.0, spacing=(SPACING_MM, SPACING_MM))))
    dataset.ImageType = ["ORIGINAL", "PRIMARY", "SINGLE PLANE"]
    dataset.AcquisitionDate, dataset.AcquisitionTime = "20260102", time
    buffer = io.BytesIO()
    dataset.save_as(buffer, enforce_file_format=True)
    return buffer.getvalue()


def test_held_depth_keeps_the_centre_projection_and_the_joint_depth():
    view = _views()["ap"]
    joint = make_transform(np.eye(3), np.array([1.0, 2.0, 3.0]))
    refined = make_transform(rotation_about_axis(np.array([0.0, 0.0, 1.0]), 0.02), np.array([1.5, 5.0, 2.0]))
    centre = np.array([2.0, -1.0, 4.0])
    held = held_depth(refined, joint, view.world_to_view, centre)

    def seen(pose):
        return (view.world_to_view @ pose @ np.append(centre, 1.0))[:3]

    np.testing.assert_allclose(seen(held)[2], seen(joint)[2], atol=1e-9)
    np.testing.assert_allclose(seen(held)[:2] / seen(held)[2], seen(refined)[:2] / seen(refined)[2], atol=1e-12)
    np.testing.assert_allclose(held[:3, :3], refined[:3, :3])


def test_a_monoplane_pair_with_head_motion_is_never_ok_and_reports_a_pose_per_run(build, tmp_path):
    phantom = make_vessel_phantom(depth=2, seed=3)
    first = make_transform(rotation_about_axis(np.array([0.3, -0.5, 0.8]), np.radians(6.0)), np.array([3.0, -2.0, 3.5]))
    direction = np.array([0.5, -0.6, 0.62]) / np.linalg.norm([0.5, -0.6, 0.62])
    motion = make_transform(rotation_about_axis(np.array([0.2, 0.9, 0.4]), np.radians(1.2)), 1.5 * direction)
    truth = {"ap": first, "lat": motion @ first}  # the head moved 1.5 mm / 1.2° between the runs
    vertices, faces = phantom.torch(torch.float64)
    files = {}
    for (name, view), time in zip(_views().items(), ("101500", "101705")):
        mask = render_hard_silhouette(vertices, faces, torch.as_tensor(view.world_to_view @ truth[name])[None],
                                      Camera.from_view(view))[0].numpy().astype(bool)
        files[name] = _xa(build, mask, name, time)
    stl = trimesh.Trimesh(phantom.vertices, phantom.faces, process=False).export(file_type="stl")
    case = load_case(mesh=stl, mesh_name="tree.stl", ap=files["ap"], lat=files["lat"])
    start = make_transform(rotation_about_axis(np.array([1.0, 0.0, 0.0]), np.radians(2.0)), np.array([1.0, 1.0, -1.0]))
    options = RegistrationOptions(initialization="given", initial_mesh_to_world=(start @ first).tolist(), starts=1,
                                  mirror_check=False)
    data = run_registration_case(case, options, tmp_path)
    assert_result_contract(data)
    confidence = data["metrics"]["confidence"]
    assert data["verdict"] == confidence["verdict"] != "ok"
    assert any("sequential runs" in reason and "10:15:00" in reason for reason in confidence["reasons"])
    acquisition = data["acquisition"]
    assert acquisition["sequential"] and acquisition["interval_s"] == pytest.approx(125.0)
    points = phantom.vertices
    for name in ("ap", "lat"):  # each run's pose: right but for the depth along its own beam
        pose = np.asarray(acquisition["run_poses"][name])
        error = pose[:3, 3] - truth[name][:3, 3]
        beam = _views()[name].world_to_view[2, :3]
        across = error - (error @ beam) * beam
        assert np.linalg.norm(across) < 0.5 and mean_distance_mm(pose, truth[name], points) < 2.0
    assert acquisition["motion"]["rotation_deg"] == pytest.approx(1.2, abs=0.4)


def test_a_later_run_of_one_plane_is_tracked_without_per_run_poses(build, tmp_path):
    """A single-plane track next to an earlier run of the other plane (sequential by their headers): the other run is
    not refitted (no run_poses, no monoplane reason); the track says what one plane cannot measure."""
    phantom = make_vessel_phantom(depth=2, seed=3)
    previous = make_transform(rotation_about_axis(np.array([0.3, -0.5, 0.8]), np.radians(6.0)), np.array([3.0, -2.0, 3.5]))
    now = make_transform(rotation_about_axis(np.array([0.2, 0.9, 0.4]), np.radians(1.0)), np.array([0.8, -0.6, 0.0])) @ previous
    vertices, faces = phantom.torch(torch.float64)
    files = {}
    for (name, view), time, pose in zip(_views().items(), ("101705", "101500"), (now, previous)):
        mask = render_hard_silhouette(vertices, faces, torch.as_tensor(view.world_to_view @ pose)[None],
                                      Camera.from_view(view))[0].numpy().astype(bool)
        files[name] = _xa(build, mask, name, time)
    stl = trimesh.Trimesh(phantom.vertices, phantom.faces, process=False).export(file_type="stl")
    case = load_case(mesh=stl, mesh_name="tree.stl", ap=files["ap"], lat=files["lat"])
    assert case.acquisition is not None and case.acquisition.sequential
    options = RegistrationOptions(mode="track", configuration="ap", initial_mesh_to_world=previous.tolist(),
                                  mirror_check=False)
    data = run_registration_case(case, options, tmp_path)
    assert_result_contract(data)
    assert "run_poses" not in data["acquisition"] and data["acquisition"]["sequential"]
    reasons = data["metrics"]["confidence"]["reasons"]
    assert not any("sequential runs" in reason for reason in reasons)
    assert data["verdict"] == "check" and "single-plane track (AP only)" in reasons[-1]
    assert data["metrics"]["tracking"]["views"] == ["ap"]
