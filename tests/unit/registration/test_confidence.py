"""Each confidence verdict from a case built to produce it (clinical-like rig, no initial pose)."""

import cv2
import numpy as np
import pytest

from dsareg_engine.simulation.clinical_rig import clinical_biplane_rig, random_visible_pose, render_masks
from dsareg_engine.mesh import TriangleMesh
from dsareg_engine.simulation.phantom import _tube, make_vessel_phantom
from dsareg_engine.registration import RegistrationOptions
from dsareg_engine.registration.solver import register
from dsareg_engine.registration.confidence import assess, outside_fraction, tolerant_f_score


@pytest.fixture(scope="module")
def rig():
    return clinical_biplane_rig(384)


@pytest.fixture(scope="module")
def truth(phantom, rig):
    return random_visible_pose(phantom, rig, np.random.default_rng(0), 40.0)


def _confidence(mesh, masks, rig, truth, **options):
    result = register(mesh, masks, rig, RegistrationOptions(ground_truth_mesh_to_world=truth.tolist(), **options))
    return result.metrics["confidence"], result.metrics["ground_truth"]["add_mm"]


def test_clean_case_is_ok(phantom, rig, truth):
    confidence, add = _confidence(phantom, render_masks(phantom, rig, truth), rig, truth)
    assert add < 1.0 and confidence["verdict"] == "ok", confidence["reasons"]


def test_masks_of_another_vessel_tree_fail(phantom, rig, truth):
    confidence, _ = _confidence(phantom, render_masks(make_vessel_phantom(seed=7), rig, truth), rig, truth)
    assert confidence["verdict"] == "failed" and "overlaps the vessels poorly" in confidence["reasons"][0]


def test_masks_two_pixels_too_wide_need_a_check(phantom, rig, truth):
    kernel = np.ones((5, 5), np.uint8)
    masks = {name: cv2.dilate(mask.astype(np.uint8), kernel).astype(bool) for name, mask in render_masks(phantom, rig, truth).items()}
    confidence, add = _confidence(phantom, masks, rig, truth)
    assert add < 1.0 and confidence["verdict"] == "check"
    assert any("borders had to move" in reason for reason in confidence["reasons"])


def test_model_half_outside_the_image_needs_a_check(phantom, rig, truth):
    moved = truth.copy()
    world = phantom.vertices @ truth[:3, :3].T + truth[:3, 3]
    shift = next(x for x in np.arange(0.0, 300.0, 5.0) if outside_fraction(rig.views["ap"], world + [x, 0, 0]) > 0.3)
    moved[0, 3] += shift
    confidence, add = _confidence(phantom, render_masks(phantom, rig, moved), rig, moved)
    assert confidence["verdict"] == "check", confidence
    assert any("outside the image" in reason for reason in confidence["reasons"])


def test_symmetric_bifurcation_is_ambiguous(rig):
    parts = [_tube(np.linspace(a, b, 16), np.full(16, radius), 12)
             for a, b, radius in [((0, -35, 0), (0, 0, 0), 3.0), ((0, 0, 0), (22, 28, 0), 2.5), ((0, 0, 0), (-22, 28, 0), 2.5)]]
    offsets = np.cumsum([0] + [len(vertices) for vertices, _ in parts[:-1]])
    vertices = np.concatenate([vertices for vertices, _ in parts])
    mesh = TriangleMesh(vertices - vertices.mean(axis=0), np.concatenate([faces + o for (_, faces), o in zip(parts, offsets)]))
    truth = random_visible_pose(mesh, rig, np.random.default_rng(3), 30.0)
    confidence, _ = _confidence(mesh, render_masks(mesh, rig, truth), rig, truth)
    assert confidence["verdict"] == "check"
    assert any(reason.startswith("ambiguous") for reason in confidence["reasons"])


def test_assess_rules_and_tolerant_fit():
    signals = {"dice": {"ap": 0.95, "lat": 0.9}, "runner_up": None, "border_shift_px": {"ap": 0.2, "lat": -0.1},
               "outside_fraction": {"ap": 0.0, "lat": 0.1}, "stopped_on_tolerance": True}
    assert assess(signals)["verdict"] == "ok"
    assert assess({**signals, "stopped_on_tolerance": False})["verdict"] == "check"
    assert assess({**signals, "dice": {"ap": 0.3, "lat": 0.9}})["verdict"] == "failed"
    # the cap met by a fit whose last Gauss-Newton steps moved the model by microns: settled, no reason to check
    capped = {**signals, "stopped_on_tolerance": False}
    assert assess({**capped, "final_step_mm": 0.002})["verdict"] == "ok"
    for travelling in (0.01, 0.3, None):
        verdict = assess({**capped, "final_step_mm": travelling})
        assert verdict["verdict"] == "check" and "iteration limit" in verdict["reasons"][0], travelling
    mask = np.zeros((40, 40), bool)
    mask[10:30, 18:22] = True
    assert tolerant_f_score(np.roll(mask, 2, axis=1), mask, 3.0) == 1.0
    assert tolerant_f_score(np.roll(mask, 10, axis=1), mask, 3.0) < 0.1


def test_partial_reason_says_when_another_part_fits_as_well():
    partial = {"dice": {"ap": 0.6, "lat": 0.6}, "runner_up": None, "outside_fraction": {"ap": 0.0, "lat": 0.0},
               "unmatched_fraction": {"ap": 0.4, "lat": 0.45}, "uncovered_fraction": {"ap": 0.01, "lat": 0.02}}
    plain = assess(partial)
    assert plain["verdict"] == "check" and "the pose fits the filled vessels" in plain["reasons"][0]
    other = assess({**partial, "part_runner_up": {"score": 0.135, "distance_mm": 6.3}})
    assert other["verdict"] == "check" and len(other["reasons"]) == 1
    assert "do not show" in other["reasons"][0] and "the pose is uncertain" in other["reasons"][0]
    assert "6 mm away" in other["reasons"][0] and "fits the filled vessels" not in other["reasons"][0]
