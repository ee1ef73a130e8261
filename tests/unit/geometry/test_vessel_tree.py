"""The vessel model as a tree: inflow, geodesic distances, downstream branches, regions to register with."""

import numpy as np
import pytest

from dsareg_engine.errors import DsaregInputError
from dsareg_engine.geometry.vessel_tree import select_region, vessel_thickness_mm, vessel_tree
from dsareg_engine.mesh import TriangleMesh
from dsareg_engine.registration.options import ModelRegion, parse_options
from dsareg_engine.simulation.phantom import _tube, make_vessel_phantom


@pytest.fixture(scope="module")
def phantom():
    return make_vessel_phantom()


def _y_tree() -> TriangleMesh:
    """A trunk (radius 3 mm) from y = −40 to 0 forking into two 2-mm branches toward ±x (separate tubes)."""
    parts = [_tube(np.linspace(a, b, 16), np.full(16, radius), 12)
             for a, b, radius in [((0, -40, 0), (0, 0, 0), 3.0), ((0, 0, 0), (25, 25, 0), 2.0), ((0, 0, 0), (-25, 25, 0), 2.0)]]
    offsets = np.cumsum([0] + [len(vertices) for vertices, _ in parts[:-1]])
    return TriangleMesh(np.concatenate([v for v, _ in parts]), np.concatenate([f + o for (_, f), o in zip(parts, offsets)]))


def test_thickness_is_the_tube_diameter():
    mesh = _y_tree()
    thickness = vessel_thickness_mm(mesh)
    trunk = mesh.vertices[:, 1] < -10
    branch = mesh.vertices[:, 1] > 10
    assert np.median(thickness[trunk]) == pytest.approx(6.0, abs=0.3)
    assert np.median(thickness[branch]) == pytest.approx(4.0, abs=0.3)


def test_inflow_is_the_trunk_end_and_distances_run_through_the_fork():
    mesh = _y_tree()
    tree = vessel_tree(mesh)
    assert mesh.vertices[tree.inflow][1] < -35  # the thick trunk's far end
    distance = tree.distances_from(tree.inflow)
    assert np.isfinite(distance).all()  # three separate tubes joined into one graph
    tip = np.argmax(mesh.vertices[:, 0])
    assert distance[tip] == pytest.approx(40 + np.hypot(25, 25), rel=0.15)


def test_downstream_of_a_branch_point_is_that_branch(phantom):
    mesh = _y_tree()
    tree = vessel_tree(mesh)
    right = np.argmin(np.linalg.norm(mesh.vertices - [8, 8, 0], axis=1))
    downstream = tree.downstream_of(int(right))
    assert np.all(mesh.vertices[downstream, 0] > 3)  # nothing of the trunk or the left branch
    assert downstream[np.argmax(mesh.vertices[:, 0])]  # the right branch's tip


@pytest.mark.parametrize("batch", [32, 3])  # 3: several Dijkstras, each stopped at its points' reach
def test_downstream_sets_batch_equals_one_at_a_time(phantom, batch):
    tree = vessel_tree(phantom)
    vertices = np.random.default_rng(2).choice(len(phantom.vertices), size=7, replace=False)
    batch = tree.downstream_sets(vertices, batch=batch)
    assert batch.shape == (7, len(phantom.vertices))
    for row, vertex in zip(batch, vertices):
        assert np.array_equal(row, tree.downstream_of(int(vertex)))


def test_phantom_inflow_is_its_trunk_base(phantom):
    tree = vessel_tree(phantom)
    trunk_base = phantom.vertices[:12].mean(axis=0)  # the first ring of the trunk (see make_vessel_phantom)
    assert np.linalg.norm(phantom.vertices[tree.inflow] - trunk_base) < 3.0


def test_regions_select_faces_and_name_the_field(phantom):
    mesh = _y_tree()
    box = select_region(mesh, ModelRegion(box_mm=[[-10, -50, -10], [10, -5, 10]]))
    assert box.n_faces > 100 and np.all(box.vertices[:, 1] <= -5)
    sphere = select_region(mesh, ModelRegion(sphere={"centre_mm": [0, -20, 0], "radius_mm": 8.0}))
    assert np.all(np.linalg.norm(sphere.vertices - [0, -20, 0], axis=1) <= 8.0)
    branch = select_region(mesh, ModelRegion(branch_near_mm=[-15, 15, 0]))
    assert np.all(branch.vertices[:, 0] < 0)
    with pytest.raises(DsaregInputError, match="options.region.sphere"):
        select_region(mesh, ModelRegion(sphere={"centre_mm": [100, 100, 100], "radius_mm": 1.0}))
    with pytest.raises(DsaregInputError, match="options.region: .*exactly one"):
        parse_options({"region": {"sphere": {"centre_mm": [0, 0, 0], "radius_mm": 5}, "box_mm": [[0, 0, 0], [1, 1, 1]]}})
    with pytest.raises(DsaregInputError, match="options.region.sphere.radius_mm"):
        parse_options({"region": {"sphere": {"centre_mm": [0, 0, 0], "radius_mm": -1}}})
    with pytest.raises(DsaregInputError, match="options.region.branch_near_mm"):
        parse_options({"region": {"branch_near_mm": [0, 0]}})
