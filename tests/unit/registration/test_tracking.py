"""Tracking over a procedure: the motion since the first pose and since the previous one, and a single-plane track
(its depth along the beam held, said so, never ``ok``)."""

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from dsareg_engine.errors import DsaregInputError
from dsareg_engine.geometry.rig import Rig
from dsareg_engine.geometry.spec import load_rig
from dsareg_engine.registration import RegistrationOptions
from dsareg_engine.registration.parameterization import random_start_poses
from dsareg_engine.registration.solver import register
from dsareg_engine.registration.tracking import (
    beam_direction,
    hold_unmeasured_depth,
    lower_verdict,
    track_metrics,
    tracking_record,
)
from dsareg_engine.render import Camera, render_hard_silhouette


def _pose(rng: np.random.Generator) -> np.ndarray:
    pose = np.eye(4)
    pose[:3, :3] = Rotation.random(random_state=int(rng.integers(1 << 30))).as_matrix()
    pose[:3, 3] = rng.normal(size=3) * 20
    return pose


def _paper_rig(size: int = 400) -> Rig:
    paper = load_rig("paper")
    return Rig({name: view.resized(size, size) for name, view in paper.views.items()}, np.eye(4))


def _expected(before: np.ndarray, after: np.ndarray, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(rotation vector in degrees, centroid displacement in mm), both world frame, computed with scipy."""
    relative = Rotation.from_matrix(after[:3, :3]) * Rotation.from_matrix(before[:3, :3]).inv()
    centre = points.mean(axis=0)
    moved = (Rotation.from_matrix(after[:3, :3]).apply(centre) + after[:3, 3]) \
        - (Rotation.from_matrix(before[:3, :3]).apply(centre) + before[:3, 3])
    return relative.as_rotvec(degrees=True), moved


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_motion_since_the_reference_and_the_previous_pose_against_scipy(seed):
    rng = np.random.default_rng(seed)
    points = rng.normal(size=(300, 3)) * 12 + [4.0, -7.0, 30.0]
    reference, previous, estimate = _pose(rng), _pose(rng), _pose(rng)
    record = tracking_record(previous, estimate, reference, points, _paper_rig(), ("ap", "lat"), None)
    assert record["views"] == ["ap", "lat"] and record["frame"] == "world" and record["reference_given"]
    assert np.allclose(record["reference_mesh_to_world"], reference)
    for key, before in (("since_reference", reference), ("since_previous", previous)):
        rotation, translation = _expected(before, estimate, points)
        motion = record[key]
        assert np.allclose(motion["rotation_vector_deg"], rotation, atol=1e-7), key
        assert motion["rotation_deg"] == pytest.approx(np.linalg.norm(rotation), abs=1e-7)
        assert np.allclose(motion["translation_vector_mm"], translation, atol=1e-9)
        assert motion["translation_mm"] == pytest.approx(np.linalg.norm(translation))
    assert record["along_beam_measured"] and record["unmeasured_view"] is None
    assert record["unmeasured_direction_world"] is None and record["depth_held_mm"] is None


def test_without_a_reference_the_previous_pose_is_the_reference():
    rng = np.random.default_rng(5)
    points = rng.normal(size=(50, 3))
    previous, estimate = _pose(rng), _pose(rng)
    record = tracking_record(previous, estimate, None, points, _paper_rig(), ("ap", "lat"), None)
    assert not record["reference_given"] and np.allclose(record["reference_mesh_to_world"], previous)
    assert record["since_reference"] == record["since_previous"]


@pytest.mark.parametrize("view", ["ap", "lat"])
def test_one_plane_names_its_beam_and_holds_the_previous_depth(view):
    rig = _paper_rig()
    world_to_view = rig.views[view].world_to_view
    centre = np.array([3.0, -2.0, 5.0])
    previous = random_start_poses(np.eye(4), centre, 2, 2.0, 2.0, seed=1)[1]
    fitted = random_start_poses(previous, centre, 2, 1.5, 3.0, seed=2)[1]  # a fit that drifted in depth too
    held, moved = hold_unmeasured_depth(fitted, previous, rig, (view,), centre)

    def in_view(pose):
        return world_to_view[:3, :3] @ (pose[:3, :3] @ centre + pose[:3, 3]) + world_to_view[:3, 3]

    assert in_view(held)[2] == pytest.approx(in_view(previous)[2])  # the previous pose's depth
    assert np.allclose(in_view(held)[:2] / in_view(held)[2], in_view(fitted)[:2] / in_view(fitted)[2])  # same pixel
    assert np.allclose(held[:3, :3], fitted[:3, :3]) and moved == pytest.approx(np.linalg.norm(held[:3, 3] - fitted[:3, 3]))
    assert hold_unmeasured_depth(fitted, previous, rig, ("ap", "lat"), centre) == (fitted, None)

    record = tracking_record(previous, held, None, centre[None], rig, (view,), moved)
    source = -world_to_view[:3, :3].T @ world_to_view[:3, 3]  # the view frame's origin in the world
    towards = held[:3, :3] @ centre + held[:3, 3] - source
    assert np.allclose(record["unmeasured_direction_world"], towards / np.linalg.norm(towards))
    assert np.allclose(beam_direction(world_to_view, held, centre), record["unmeasured_direction_world"])
    assert not record["along_beam_measured"] and record["unmeasured_view"] == view and record["views"] == [view]


def test_one_plane_is_never_ok_and_a_failure_stays_failed():
    rig, rng = _paper_rig(), np.random.default_rng(3)
    previous, estimate, points = _pose(rng), _pose(rng), rng.normal(size=(20, 3))
    ok = {"verdict": "ok", "reasons": []}
    metrics = track_metrics(previous, estimate, None, points, rig, ("lat",), None, ok)  # the fit's own depth
    record = metrics["tracking"]
    assert metrics["mode"] == "track" and metrics["motion"] == record["since_previous"] and record["depth"] == "fit"
    beam = np.asarray(record["unmeasured_direction_world"])
    assert record["along_beam_mm"] == pytest.approx(np.dot(record["since_previous"]["translation_vector_mm"], beam),
                                                    abs=1e-4)
    assert ok["verdict"] == "check" and "LAT beam" in ok["reasons"][-1] and "not measured" in ok["reasons"][-1]
    assert f"{record['along_beam_mm']:+.2f} mm along it" in ok["reasons"][-1]
    held = {"verdict": "ok", "reasons": []}
    record = track_metrics(previous, estimate, None, points, rig, ("lat",), 0.4, held)["tracking"]
    assert record["depth"] == "previous" and record["depth_held_mm"] == 0.4 and held["verdict"] == "check"
    assert "keeps the previous pose's depth" in held["reasons"][-1]
    failed = {"verdict": "failed", "reasons": ["dice"]}
    track_metrics(previous, estimate, None, points, rig, ("ap",), 0.4, failed)
    assert failed["verdict"] == "failed" and len(failed["reasons"]) == 2
    both = {"verdict": "ok", "reasons": []}
    track_metrics(previous, estimate, None, points, rig, ("ap", "lat"), None, both)
    assert both == {"verdict": "ok", "reasons": []}
    lower_verdict(None, "x")  # no confidence: nothing to lower
    with pytest.raises(DsaregInputError) as caught:
        track_metrics(previous, estimate, (2 * np.eye(4)).tolist(), points, rig, ("ap",), None, ok)
    assert caught.value.field == "options.reference_mesh_to_world"


def _masks(mesh, rig, pose):
    vertices, faces = mesh.torch(torch.float64)
    return {name: render_hard_silhouette(vertices, faces, torch.as_tensor(view.world_to_view @ pose)[None],
                                         Camera.from_view(view))[0].numpy() for name, view in rig.views.items()}


def test_engine_tracks_a_later_run_of_one_plane(phantom):
    """A later AP run alone: the pose follows the motion across the AP beam, says the motion along it is not
    measured (or holds the previous depth there when asked), reports the motion since the procedure's first pose,
    and says `check` where both planes say `ok`."""
    rig = _paper_rig(400)
    reference = np.eye(4)
    previous = random_start_poses(reference, phantom.centroid, 2, 1.0, 1.0, seed=4)[1]
    truth = random_start_poses(previous, phantom.centroid, 2, 2.0, 2.5, seed=6)[1]
    masks = _masks(phantom, rig, truth)
    common = {"mode": "track", "initial_mesh_to_world": previous.tolist(), "reference_mesh_to_world": reference.tolist(),
              "ground_truth_mesh_to_world": truth.tolist()}
    one = register(phantom, masks, rig, RegistrationOptions(configuration="ap", **common))
    kept = register(phantom, masks, rig, RegistrationOptions(configuration="ap", single_plane_depth="previous", **common))
    both = register(phantom, masks, rig, RegistrationOptions(**common))
    assert both.metrics["tracking"]["along_beam_measured"] and both.metrics["ground_truth"]["add_mm"] < 0.05
    assert both.metrics["confidence"]["verdict"] == "ok"
    centre = phantom.vertices.mean(axis=0)
    for result in (one, kept):
        record = result.metrics["tracking"]
        assert record["views"] == ["ap"] and not record["along_beam_measured"] and record["unmeasured_view"] == "ap"
        assert result.metrics["confidence"]["verdict"] == "check"
        assert "single-plane track (AP only)" in result.metrics["confidence"]["reasons"][-1]
        error = result.mesh_to_world[:3, :3] @ centre + result.mesh_to_world[:3, 3] - (truth[:3, :3] @ centre + truth[:3, 3])
        beam = np.asarray(record["unmeasured_direction_world"])
        assert np.linalg.norm(error - (error @ beam) * beam) < 0.1  # across the beam: measured
        assert result.metrics["ground_truth"]["rotation_error_deg"] < 0.2
        rotation, translation = _expected(reference, result.mesh_to_world, phantom.vertices)
        assert np.allclose(record["since_reference"]["rotation_vector_deg"], rotation, atol=1e-6)
        assert np.allclose(record["since_reference"]["translation_vector_mm"], translation, atol=1e-6)
        true_rotation, _ = _expected(reference, truth, phantom.vertices)
        assert np.linalg.norm(rotation - true_rotation) < 0.2
    assert one.metrics["tracking"]["depth"] == "fit" and one.metrics["tracking"]["depth_held_mm"] is None
    assert kept.metrics["tracking"]["depth"] == "previous" and kept.metrics["tracking"]["depth_held_mm"] > 0
    depth_axis = rig.views["ap"].world_to_view[2, :3]  # the view's z axis in the world: the held depth
    assert abs(np.dot(kept.metrics["tracking"]["since_previous"]["translation_vector_mm"], depth_axis)) < 1e-6
