"""The mirror check: a model with one axis flipped is registered, found mirrored and named ``failed``;
a normal model never pays for it."""

import numpy as np
import pytest

from dsareg_engine.geometry.rig import Rig
from dsareg_engine.mesh import TriangleMesh
from dsareg_engine.registration import parse_options
from dsareg_engine.registration.solver import register
from dsareg_engine.registration.mirror import flipped_axis, mirrored, needs_mirror_check
from dsareg_engine.simulation.clinical_rig import (clinical_biplane_rig, random_visible_pose, render_masks,
                                                   uniform_rotation)
from dsareg_engine.simulation.phantom import make_vessel_phantom

FLIPS = {"x": 0, "y": 1, "z": 2}


def _flipped(mesh: TriangleMesh, axis: str) -> TriangleMesh:
    """The model with one axis flipped through its centre, as a wrong export writes it."""
    vertices = mesh.vertices.copy()
    index = FLIPS[axis]
    vertices[:, index] = 2.0 * mesh.centroid[index] - vertices[:, index]
    return TriangleMesh(vertices, np.ascontiguousarray(mesh.faces[:, ::-1]))


def _kabsch(source: np.ndarray, target: np.ndarray) -> np.ndarray:
    """The rotation ``(3, 3)`` best taking centred ``source`` ``(N, 3)`` onto ``target`` (least squares)."""
    a, b = source - source.mean(0), target - target.mean(0)
    u, _, vt = np.linalg.svd(a.T @ b)
    d = np.sign(np.linalg.det(vt.T @ u.T))
    return vt.T @ np.diag([1.0, 1.0, d]) @ u.T


@pytest.mark.parametrize("axis", ["x", "y", "z"])
def test_the_flipped_axis_is_read_from_the_mirrors_pose(axis):
    """Independent of the module's formula: the pose that lays the mirrored model onto the true vessels,
    found by least squares on the points, against the true pose given."""
    mesh = make_vessel_phantom(depth=1)
    true = np.eye(4)
    true[:3, :3] = uniform_rotation(np.random.default_rng(3))
    model = mirrored(_flipped(mesh, axis))  # what the mirror fit registers
    fitted = np.eye(4)
    fitted[:3, :3] = _kabsch(model.vertices, mesh.vertices @ true[:3, :3].T)
    assert flipped_axis(true, fitted) == axis
    assert flipped_axis(None, fitted) is None


def test_the_mirror_is_tried_only_when_the_fit_is_poor_and_not_partial_filling():
    assert not needs_mirror_check({"signals": {"dice": {"ap": 0.95, "lat": 0.93}}, "reasons": []})
    assert needs_mirror_check({"signals": {"dice": {"ap": 0.44, "lat": 0.93}}, "reasons": ["ap: ..."]})
    partial = "the model has vessels the images do not show (ap 40% / lat 38% ...)"
    assert not needs_mirror_check({"signals": {"dice": {"ap": 0.55, "lat": 0.6}}, "reasons": [partial]})


@pytest.fixture(scope="module")
def case():
    mesh = make_vessel_phantom(depth=3)
    rig = clinical_biplane_rig(size_px=160)
    pose = random_visible_pose(mesh, rig, np.random.default_rng(1))
    return mesh, rig, pose, render_masks(mesh, rig, pose)


def test_a_mirrored_model_fails_naming_the_mirror_and_the_axis(case):
    mesh, rig, pose, masks = case
    options = parse_options({"device": "cpu", "initial_mesh_to_world": pose.tolist(), "starts": 2})
    result = register(_flipped(mesh, "y"), masks, Rig(views=rig.views), options)
    confidence = result.metrics["confidence"]
    assert confidence["verdict"] == "failed" and result.to_dict()["verdict"] == "failed"
    assert confidence["reasons"][0].startswith("the model seems mirrored (its y axis flipped")
    assert "LPS/RAS" in confidence["reasons"][0]
    mirror = confidence["signals"]["mirror"]
    assert mirror["mirrored"] and mirror["axis"] == "y" and min(mirror["dice"].values()) > 0.85
    assert result.metrics["seconds"]["mirror"] > 0


def test_a_normal_model_is_not_called_mirrored_and_pays_nothing(case):
    mesh, rig, pose, masks = case
    result = register(mesh, masks, Rig(views=rig.views), parse_options({"device": "cpu"}))
    confidence = result.metrics["confidence"]
    assert confidence["verdict"] == "ok", confidence["reasons"]
    assert "mirror" not in confidence["signals"] and "mirror" not in result.metrics["seconds"]


@pytest.mark.parametrize("check", [True, False])
def test_the_mirror_check_option_decides_whether_a_poor_fit_registers_the_mirror(check):
    """``mirror_check`` off (a worker's warm-up job, whose tiny fit is poor by design): no mirror registered, the
    confidence as it was; on (the default): the mirror of the model is registered from a rotation search."""
    from types import SimpleNamespace

    from dsareg_engine.registration.mirror import with_mirror_check

    mesh = make_vessel_phantom(depth=1)
    poor = {"verdict": "check", "signals": {"dice": {"ap": 0.4, "lat": 0.5}}, "reasons": ["ap: poor overlap"]}
    result = SimpleNamespace(metrics={"confidence": poor})
    fitted = []

    def register_with(model, masks, rig, options):
        fitted.append((model, options))
        return SimpleNamespace(mesh_to_world=np.eye(4), metrics={"confidence": {"signals": {"dice": {"ap": 0.45,
                                                                                                      "lat": 0.5}}}})

    options = parse_options({"device": "cpu", "mirror_check": check})
    out = with_mirror_check(result, mesh, {}, clinical_biplane_rig(size_px=16), options, register_with)
    assert parse_options({}).mirror_check  # on by default
    if not check:
        assert fitted == [] and out.metrics["confidence"] == poor and "seconds" not in out.metrics
        return
    (model, search), = fitted
    assert np.allclose(model.vertices, mirrored(mesh).vertices) and search.initialization == "search"
    assert out.metrics["confidence"]["signals"]["mirror"]["mirrored"] is False
