"""Geometry convention checked against independent computations."""

import json

import numpy as np
import pytest

from dsareg_engine.errors import DsaregInputError
from dsareg_engine.geometry.rig import (
    ViewGeometry,
    biplane_rig,
    view_from_detector_pose,
    view_from_projection_matrix,
)
from dsareg_engine.geometry.file import paper_focal_px
from dsareg_engine.geometry.spec import load_rig
from dsareg_engine.geometry.pose import make_transform, rotation_about_axis


def _view(mirrored=False, seed=0):
    rng = np.random.default_rng(seed)
    rotation = rotation_about_axis(rng.normal(size=3), 0.7)
    if mirrored:
        rotation = np.diag([1.0, -1.0, 1.0]) @ rotation
    return ViewGeometry((640, 480), (0.3, 0.25), 1000.0, (300.2, 250.7), make_transform(rotation, [5.0, -3.0, 700.0]))


def test_projection_follows_the_written_formula():
    view = _view()
    point = np.array([[10.0, -20.0, 5.0]])
    x, y, z = view.world_to_view[:3, :3] @ point[0] + view.world_to_view[:3, 3]
    expected = [300.2 + (1000.0 / 0.3) * x / z, 250.7 + (1000.0 / 0.25) * y / z]
    assert np.allclose(view.project(point)[0], expected)
    homogeneous = view.projection_matrix @ np.append(point[0], 1.0)
    assert np.allclose(homogeneous[:2] / homogeneous[2], expected)


def test_default_principal_point_is_pixel_centre_of_image():
    spec = {"views": {"ap": {"image_size": [5, 3], "pixel_spacing_mm": [1, 1], "sid_mm": 10, "world_to_view": np.eye(4).tolist()}}}
    assert load_rig(spec).views["ap"].principal_point_px == (2.0, 1.0)


def test_resize_keeps_detector_extent_and_pixel_centres():
    view = _view()
    half = view.resized(320, 240)
    point = np.array([[3.0, 4.0, -2.0]])
    u, v = view.project(point)[0]
    u2, v2 = half.project(point)[0]
    # A continuous image coordinate c maps to (c + 0.5) * s - 0.5.
    assert np.allclose([u2, v2], [(u + 0.5) * 0.5 - 0.5, (v + 0.5) * 0.5 - 0.5])
    assert half.sid_mm == view.sid_mm


@pytest.mark.parametrize("mirrored", [False, True])
@pytest.mark.parametrize("scale", [1.0, -3.5])
def test_projection_matrix_round_trip(mirrored, scale):
    view = _view(mirrored)
    recovered = view_from_projection_matrix(scale * view.projection_matrix, view.image_size, view.pixel_spacing_mm)
    assert np.allclose(recovered.world_to_view, view.world_to_view, atol=1e-9)
    assert recovered.sid_mm == pytest.approx(1000.0)
    assert np.allclose(recovered.principal_point_px, view.principal_point_px)
    assert recovered.is_mirrored == mirrored


def test_projection_matrix_with_inconsistent_spacing_is_rejected():
    view = _view()
    with pytest.raises(DsaregInputError, match="pixel_spacing_mm"):
        view_from_projection_matrix(view.projection_matrix, view.image_size, (0.3, 0.3))


def test_rad_style_detector_pose_projects_onto_the_detector_pixel():
    """A point on the detector at pixel (i, j) must project to (i, j): independent of our algebra."""
    rng = np.random.default_rng(3)
    detector_to_world = make_transform(rotation_about_axis(rng.normal(size=3), 1.1), rng.normal(size=3) * 50)
    spacing = (0.4, 0.3)
    source_detector = np.array([200.0, 150.0, 1100.0])  # in detector mm, z toward the source
    source_world = detector_to_world[:3, :3] @ source_detector + detector_to_world[:3, 3]
    view = view_from_detector_pose((1000, 800), spacing, detector_to_world, source_world)
    assert view.is_mirrored
    assert view.sid_mm == pytest.approx(1100.0)
    assert np.allclose(view.principal_point_px, (500.0, 500.0))
    i, j = 123.0, 456.0
    on_detector = detector_to_world[:3, :3] @ np.array([i * spacing[0], j * spacing[1], 0.0]) + detector_to_world[:3, 3]
    # Any point on the ray source → detector pixel projects to the same pixel.
    midway = 0.5 * (on_detector + source_world)
    assert np.allclose(view.project(np.stack([on_detector, midway])), [[i, j], [i, j]], atol=1e-6)


def test_biplane_rig_angle_is_what_was_asked():
    view = _view()
    axis_perpendicular_to_ray = view.world_to_view[1, :3]  # the view's +y axis in world coordinates
    rig = biplane_rig(view, angle_deg=107.0, axis_world=axis_perpendicular_to_ray)
    assert rig.angle_between_views_deg() == pytest.approx(107.0, abs=1e-6)


def test_paper_preset_matches_pytorch3d_fov_camera():
    """PyTorch3D FoV camera: x_ndc = X/(Z tan 30°), pixel i = (W/2)(1 − x_ndc) − 0.5 (+X left)."""
    rig = load_rig("paper")
    assert paper_focal_px() == pytest.approx(692.82, abs=0.01)
    ap = rig.views["ap"]
    point = np.array([3.0, 7.0, -11.0])
    # AP camera at (-150, 0, 0) looking at the origin with up +y: PyTorch3D's look_at
    # gives view axes X = up × z = (0, 0, -1), Y = (0, 1, 0), Z = (1, 0, 0).
    eye = np.array([-150.0, 0.0, 0.0])
    X, Y, Z = (point - eye) @ np.array([0.0, 0.0, -1.0]), (point - eye) @ np.array([0.0, 1.0, 0.0]), (point - eye) @ np.array([1.0, 0.0, 0.0])
    t = np.tan(np.radians(30.0))
    expected = [400 * (1 - X / (Z * t)) - 0.5, 400 * (1 - Y / (Z * t)) - 0.5]
    assert np.allclose(ap.project(point[None])[0], expected)
    assert rig.angle_between_views_deg() == pytest.approx(90.0)


@pytest.mark.parametrize(
    "matrix, message",
    [
        ([[2, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]], "not orthonormal"),
        ([[1, 0, 0], [0, 1, 0], [0, 0, 1]], "shape"),
        ([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 1, 1]], "last row"),
        ([[1, 0, 0, float("nan")], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]], "NaN"),
    ],
)
def test_geometry_file_rejects_bad_world_to_view(matrix, message):
    spec = {"views": {"ap": {"image_size": [10, 10], "pixel_spacing_mm": [1, 1], "sid_mm": 100, "world_to_view": matrix}}}
    with pytest.raises(DsaregInputError, match=message) as info:
        load_rig(json.dumps(spec))
    assert "geometry.views.ap" in str(info.value)


def test_geometry_file_errors_name_the_field():
    with pytest.raises(DsaregInputError, match="sid_mm"):
        load_rig({"views": {"ap": {"image_size": [10, 10], "pixel_spacing_mm": [1, 1], "sid_mm": -5, "world_to_view": np.eye(4).tolist()}}})
    with pytest.raises(DsaregInputError, match="preset"):
        load_rig("no-such-preset")
    with pytest.raises(DsaregInputError, match="JSON"):
        load_rig("{not json")


def test_lat_from_ap_in_geometry_file():
    view = _view()
    axis = view.world_to_view[1, :3].tolist()  # perpendicular to the central ray
    spec = {"views": {"ap": view.to_dict()}, "lat_from_ap": {"angle_deg": 75.0, "axis_world": axis}}
    assert load_rig(spec).angle_between_views_deg() == pytest.approx(75.0)
