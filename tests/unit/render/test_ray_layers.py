"""The stretches a ray crosses: lengths and middles against boxes whose geometry is known in closed form."""

from __future__ import annotations

import numpy as np
import trimesh

from dsareg_engine.render.ray_layers import ray_stretches

FOCAL_PX = (200.0, 200.0)
CENTRE_PX = (15.0, 15.0)
SIZE = (31, 31)


def _boxes(centres, side_mm: float):
    parts = [trimesh.creation.box(extents=(side_mm,) * 3).apply_translation(c) for c in centres]
    return np.concatenate([p.vertices for p in parts]), np.concatenate(
        [p.faces + 8 * k for k, p in enumerate(parts)])


def test_two_boxes_on_the_central_ray_are_two_stretches_with_their_centres_as_middles():
    vertices, faces = _boxes([(0.0, 0.0, 100.0), (0.0, 0.0, 130.0)], 10.0)
    stretches = ray_stretches(vertices, faces, FOCAL_PX, CENTRE_PX, SIZE)
    assert stretches.layers[15, 15] == 2 and stretches.covered[15, 15]
    assert np.allclose(stretches.length_mm[15, 15, :2], 10.0)
    pixel, length, middle = stretches.middles_in_view(FOCAL_PX, CENTRE_PX)
    central = pixel == 15 * SIZE[0] + 15
    assert np.allclose(np.sort(middle[central][:, 2]), [100.0, 130.0]) and np.allclose(middle[central][:, :2], 0.0)


def test_an_oblique_ray_through_a_box_has_the_chord_and_middle_of_its_slab():
    """Off-centre pixel (u, v) = (20, 15): the ray (5/200, 0, 1) crosses the slab 95 ≤ z ≤ 105 of a box wide enough
    in x: the chord is 10 mm / cos, the middle at z = 100 on that ray."""
    vertices, faces = _boxes([(0.0, 0.0, 100.0)], 10.0)
    vertices = vertices * np.array([4.0, 1.0, 1.0])  # 40 mm wide in x, the same slab in z
    stretches = ray_stretches(vertices, faces, FOCAL_PX, CENTRE_PX, SIZE)
    ray = np.array([5.0 / 200.0, 0.0, 1.0])
    assert np.isclose(stretches.length_mm[15, 20, 0], 10.0 * np.linalg.norm(ray))
    pixel, _, middle = stretches.middles_in_view(FOCAL_PX, CENTRE_PX)
    assert np.allclose(middle[pixel == 15 * SIZE[0] + 20][0], 100.0 * ray)
