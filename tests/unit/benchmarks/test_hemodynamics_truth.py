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
