"""The review files: the C-arm in world mm (checked by projecting it back), the model file as given, the layers.
A whole job writing them: tests/unit/test_warmup.py."""

from __future__ import annotations

import numpy as np

from dsareg_engine.geometry.pose import make_transform, rotation_about_axis
from dsareg_engine.geometry.rig import ViewGeometry
from dsareg_engine.io.review_files import (MASK_BIT, UNFILLED_BIT, detector_geometry, layer_image, obj_as_given,
                                          registered_image)


def _view(mirrored: bool) -> ViewGeometry:
    turn = rotation_about_axis(np.array([0.3, 1.0, 0.2]), 0.7)
    world_to_view = make_transform(turn, np.array([5.0, -12.0, 700.0]))
    if mirrored:
        world_to_view = np.diag([1.0, -1.0, 1.0, 1.0]) @ world_to_view
    return ViewGeometry(image_size=(120, 80), pixel_spacing_mm=(0.4, 0.3), sid_mm=1100.0,
                        principal_point_px=(63.0, 37.5), world_to_view=world_to_view)


def test_detector_corners_project_onto_the_image_corners_and_lie_at_sid():
    for mirrored in (False, True):
        view = _view(mirrored)
        detector = detector_geometry(view, 0.25)
        corners = np.array(detector["corners_mm"])
        # independent check: the rig's own projection takes the corners back to the image's outer pixel edges
        assert np.allclose(view.project(corners), [[-0.5, -0.5], [119.5, -0.5], [119.5, 79.5], [-0.5, 79.5]],
                           atol=1e-3)
        source = np.array(detector["source_mm"])
        beam = np.linalg.inv(view.world_to_view)[:3, 2]  # the central ray's direction in the world
        assert np.allclose((corners - source) @ beam, 1100.0, atol=1e-3)  # the plane z = sid
        top = corners[1] - corners[0]
        assert np.isclose(np.linalg.norm(top), 120 * 0.4, atol=1e-3)  # W pixels of du
        assert detector["image_size_px"] == [120, 80] and detector["mm_per_px_at_model"] == 0.25


def test_obj_as_given_keeps_order_duplicates_and_polygons():
    data = b"# x\nv 0 0 0\nv 1 0 0\nv 1 1 0\nv 1 0 0\nvn 0 0 1\nf 1/1/1 2//1 3 4\nv 2 2 2\nf -1 -2 -3\n"
    vertices, faces = obj_as_given(data)
    assert vertices.tolist() == [[0, 0, 0], [1, 0, 0], [1, 1, 0], [1, 0, 0], [2, 2, 2]]  # the duplicate kept
    assert faces.tolist() == [[0, 1, 2], [0, 2, 3], [4, 3, 2]]


def test_layers_carry_each_outline_and_the_mask_bits():
    initial = np.zeros((20, 20), bool)
    initial[2:8, 2:8] = True
    registered = np.zeros((20, 20), bool)
    registered[10:16, 10:16] = True
    mask = registered.copy()
    unfilled = np.zeros_like(mask)
    unfilled[15, 15] = True
    layers = layer_image(initial, registered, mask, unfilled)
    assert (layers[..., 0] == 255).sum() == 20 and layers[4, 4, 0] == 0  # a 6x6 square's edge, not its inside
    assert (layers[..., 1] == 255).sum() == 20
    assert ((layers[..., 2] & MASK_BIT) > 0).sum() == 36 and ((layers[..., 2] & UNFILLED_BIT) > 0).sum() == 1
    image = registered_image(np.linspace(0, 1, 400).reshape(20, 20))
    assert image.dtype == np.uint8 and image.min() == 0 and image.max() == 255

