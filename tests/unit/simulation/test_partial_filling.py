"""Simulated partial visibility: early filling, one injected branch, a model with an extra territory."""

import numpy as np
import pytest
from scipy.spatial import cKDTree

from dsareg_engine.geometry.vessel_tree import vessel_tree
from dsareg_engine.simulation.partial_filling import bolus_front, early_filling, extra_territory, selective_injection
from dsareg_engine.simulation.phantom import make_vessel_phantom


@pytest.fixture(scope="module")
def phantom_tree():
    mesh = make_vessel_phantom()
    return mesh, vessel_tree(mesh)


@pytest.mark.parametrize("fraction", [0.4, 0.6])
def test_early_filling_keeps_the_faces_nearest_the_inflow(phantom_tree, fraction):
    mesh, tree = phantom_tree
    case = early_filling(mesh, fraction, tree)
    assert case.visible_fraction == pytest.approx(fraction, abs=0.02)
    assert case.visible.n_faces == pytest.approx(fraction * mesh.n_faces, rel=0.05)
    inflow = mesh.vertices[tree.inflow]
    assert np.min(np.linalg.norm(case.visible.vertices - inflow, axis=1)) < 1e-9  # the inflow is filled
    # every visible vertex is nearer the inflow (along the tree) than every hidden one, to within a face
    distance = tree.distances_from(tree.inflow)
    visible = np.isin(np.round(mesh.vertices, 9).view("f8,f8,f8"), np.round(case.visible.vertices, 9).view("f8,f8,f8")).ravel()
    assert distance[visible].max() <= distance[~visible].min() + 3.0


def test_a_bolus_front_is_not_the_geodesic_front(phantom_tree):
    mesh, tree = phantom_tree
    assert bolus_front(mesh, 0.5, tree, speed_exponent=0.0).visible.n_faces == early_filling(mesh, 0.5, tree).visible.n_faces
    front, geodesic = bolus_front(mesh, 0.5, tree), early_filling(mesh, 0.5, tree)
    assert front.visible_fraction == pytest.approx(0.5, abs=0.02)
    assert np.min(np.linalg.norm(front.visible.vertices - mesh.vertices[tree.inflow], axis=1)) < 1e-9
    # the same share of faces, but another set of them: not the geodesic front the proximal parts are cut by
    shown = {name: set(_face_keys(mesh, case.visible)) for name, case in (("front", front), ("geodesic", geodesic))}
    assert len(shown["front"] & shown["geodesic"]) < 0.9 * len(shown["front"] | shown["geodesic"])


def _face_keys(mesh, part) -> list:
    """Each face of ``part`` as the sorted indices of its vertices in ``mesh``."""
    index = cKDTree(mesh.vertices).query(part.vertices)[1]
    return [tuple(face) for face in np.sort(index[part.faces], axis=1)]


def test_selective_injection_is_one_branch_away_from_the_inflow(phantom_tree):
    mesh, tree = phantom_tree
    case = selective_injection(mesh, 0.3, np.random.default_rng(1), tree)
    assert case.visible_fraction == pytest.approx(0.3, abs=0.1)
    inflow = mesh.vertices[tree.inflow]
    assert np.min(np.linalg.norm(case.visible.vertices - inflow, axis=1)) > 10.0


def test_extra_territory_doubles_the_model_and_shows_the_original(phantom_tree):
    mesh, tree = phantom_tree
    case = extra_territory(mesh, tree)
    assert case.model.n_faces == 2 * mesh.n_faces and case.visible is mesh and case.visible_fraction == 0.5
    copy = case.model.vertices[len(mesh.vertices):]
    assert np.linalg.norm(copy.mean(axis=0) - mesh.centroid) > 10.0  # the copy spreads away from the original
    a, b, c = (case.model.vertices[case.model.faces[mesh.n_faces:, k]] for k in range(3))
    normals = np.cross(b - a, c - a)
    outward = ((a + b + c) / 3 - copy.mean(axis=0))
    assert np.mean(np.sum(normals * outward, axis=1) > 0) > 0.5  # the mirrored copy still winds outward


def test_reflux_injection_is_a_partly_filled_branch_with_reflux(phantom_tree):
    from dsareg_engine.simulation.partial_filling import reflux_injection

    mesh, tree = phantom_tree
    case = reflux_injection(mesh, 0.5, np.random.default_rng(4), tree, reflux_mm=(10.0, 10.0))
    assert case.kind == "reflux_injection" and 0.15 < case.visible_fraction < 0.85
    inflow = mesh.vertices[tree.inflow]
    assert np.min(np.linalg.norm(case.visible.vertices - inflow, axis=1)) > 5.0  # the inflow is not filled


def test_foreign_territory_joins_another_tree_at_the_inflow(phantom_tree):
    from dsareg_engine.simulation.partial_filling import foreign_territory

    mesh, tree = phantom_tree
    other = make_vessel_phantom(seed=3)
    case = foreign_territory(mesh, other, tree)
    assert case.model.n_faces == mesh.n_faces + other.n_faces and case.visible is mesh
    placed = case.model.vertices[len(mesh.vertices):]
    inflow = mesh.vertices[tree.inflow]
    assert np.min(np.linalg.norm(placed - inflow, axis=1)) < 1e-6  # its inflow on the mesh's
    assert (placed.mean(axis=0) - inflow) @ (mesh.centroid - inflow) < 0  # spreading away from the mesh
    rms = lambda v: np.sqrt(((v - v.mean(axis=0)) ** 2).sum(axis=1).mean())
    assert rms(placed) == pytest.approx(rms(mesh.vertices), rel=1e-6)


def test_images_holding_more_turn_a_case_round(phantom_tree):
    from dsareg_engine.simulation.partial_filling import images_hold_more

    mesh, tree = phantom_tree
    case = images_hold_more(extra_territory(mesh, tree), "image_extra_territory")
    assert case.model is mesh and case.visible.n_faces == 2 * mesh.n_faces  # the images show both territories
    assert case.kind == "image_extra_territory" and case.visible_fraction == 2.0


def test_missing_small_branches_drops_the_thinnest_distal_branches(phantom_tree):
    from dsareg_engine.simulation.partial_filling import missing_small_branches

    mesh, tree = phantom_tree
    case = missing_small_branches(mesh, 0.25, np.random.default_rng(0), tree)
    assert case.visible is mesh and case.kind == "image_missing_small_branches"
    assert 0.70 <= case.model.n_faces / mesh.n_faces <= 0.75  # about a quarter dropped, not much more
    assert case.visible_fraction == pytest.approx(mesh.n_faces / case.model.n_faces)
    kept = cKDTree(case.model.vertices).query(mesh.vertices)[0] < 1e-9
    assert kept[tree.inflow]  # the trunk stays
    # what is dropped is thin: its median thickness well under the kept vessels'
    assert np.median(tree.thickness_mm[~kept]) < 0.9 * np.median(tree.thickness_mm[kept])
