"""The hemodynamics benchmark's truth (benchmarks/engine/hemodynamics.py): the winding number against an independent
inside test, and never-reached vertices inside a filled vessel counted apart."""

from __future__ import annotations

import numpy as np
import trimesh

from benchmarks.engine.hemodynamics import in_filled_lumen, winding_numbers
from dsareg_engine.mesh import TriangleMesh


def test_winding_number_agrees_with_an_inside_test_on_a_closed_and_an_open_tube():
    tube = trimesh.creation.cylinder(radius=2.0, height=20.0, sections=24)
    points = np.random.default_rng(0).uniform(-4.0, 4.0, size=(400, 3)) * [1.0, 1.0, 3.0]
    points = points[np.abs(np.linalg.norm(points[:, :2], axis=1) - 2.0) > 0.3]  # not on the wall
    inside = (np.linalg.norm(points[:, :2], axis=1) < 2.0) & (np.abs(points[:, 2]) < 10.0)  # analytic
    assert 20 < inside.sum() < len(points) - 20
    w = winding_numbers(points, np.asarray(tube.vertices), np.asarray(tube.faces))
    np.testing.assert_allclose(np.abs(w), inside.astype(float), atol=1e-6)
    walls = ~np.isin(np.arange(len(tube.faces)), np.flatnonzero(np.abs(tube.face_normals[:, 2]) > 0.99))
    middle = np.abs(points[:, 2]) < 5.0
    open_w = np.abs(winding_numbers(points[middle], np.asarray(tube.vertices), np.asarray(tube.faces)[walls]))
    assert ((open_w > 0.5) == inside[middle]).all()


def test_a_blocked_branch_starting_inside_its_filled_parent_is_counted_in_the_lumen():
    parent = trimesh.creation.cylinder(radius=2.0, height=20.0, sections=24)
    branch = trimesh.creation.cylinder(radius=0.8, height=10.0, sections=12)
    branch.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [0, 1, 0]))
    branch.apply_translation([5.5, 0.0, 0.0])  # from x = 0.5 (inside the parent) to x = 10.5
    both = trimesh.util.concatenate([parent, branch])
    never = np.zeros(len(both.vertices), bool)
    never[len(parent.vertices):] = True  # the branch never fills
    inside = in_filled_lumen(TriangleMesh(np.asarray(both.vertices), np.asarray(both.faces)), never)
    branch_x = both.vertices[never][:, 0]
    assert inside[never].sum() == (np.abs(branch_x) < 2.0).sum() > 0  # the end inside the parent only
    assert not inside[~never].any()


RING, SIDES, BLOCK = 16, 12, 16 * 12 + 2  # the phantom's rings per tube, vertices per ring, vertices per tube


def _ring_centroids(vertices: np.ndarray) -> np.ndarray:
    """``(V, 3)`` each ring vertex's ring centroid (the tube's centreline point by construction); caps: NaN."""
    index = np.arange(len(vertices))
    local = index % BLOCK
    out = np.full(vertices.shape, np.nan)
    ring = local < RING * SIDES
    first = index[ring] - local[ring] % SIDES
    out[ring] = np.mean([vertices[first + k] for k in range(SIDES)], axis=0)
    return out


def test_cross_section_centres_are_the_tube_axis():
    from benchmarks.engine.hemodynamics import cross_section_centres
    from dsareg_engine.simulation.phantom import make_vessel_phantom

    tube = make_vessel_phantom(seed=1, depth=0)
    middle = np.flatnonzero((np.arange(len(tube.vertices)) >= 2 * SIDES) & (np.arange(len(tube.vertices)) < (RING - 2) * SIDES))
    centres = cross_section_centres(tube, middle)
    np.testing.assert_allclose(centres, _ring_centroids(tube.vertices)[middle], atol=0.03)


def test_a_blocked_branch_whose_cross_sections_start_in_its_filled_sibling_is_counted_by_its_cross_sections():
    """Both children of the phantom start at the parent's end, their first rings centred there: the blocked child's
    first cross-sections lie in the filled parent and sibling although some of its first wall vertices lie outside
    them (the wall-point test missed those). Cross-sections far from every filled tube are not counted."""
    from dsareg_engine.simulation.phantom import make_vessel_phantom

    mesh = make_vessel_phantom(seed=0, depth=1)
    never = (np.arange(len(mesh.vertices)) // BLOCK) == 1  # the first child popped: blocked
    inside = in_filled_lumen(mesh, never)
    first_ring = np.flatnonzero(never)[:SIDES]
    assert inside[first_ring].all()
    filled = ~never[mesh.faces].any(axis=1)
    wall = np.abs(winding_numbers(mesh.vertices[first_ring], mesh.vertices, mesh.faces[filled])) > 0.5
    assert not wall.all()  # the wall points alone miss some of them
    centroids = _ring_centroids(mesh.vertices)
    filled_axis = centroids[~never & np.isfinite(centroids[:, 0])]
    blocked = np.flatnonzero(never & np.isfinite(centroids[:, 0]))
    gap = np.linalg.norm(centroids[blocked][:, None] - filled_axis[None], axis=2).min(axis=1)
    radius = np.linalg.norm(mesh.vertices[blocked] - centroids[blocked], axis=1)
    reach = radius + 2.2 + 1.5  # its radius + the trunk's (the largest filled) + the ring spacing
    far = blocked[gap > reach]
    assert len(far) > 5 * SIDES and not inside[far].any()
