"""The per-vertex order contract: values per vertex of the model file as given (OBJ v lines, duplicates included)."""

from __future__ import annotations

import numpy as np

from dsareg_engine.hemodynamics.model_points import transfer, vertices_as_given, vessel_points
from dsareg_engine.io.mesh_io import read_mesh
from dsareg_engine.simulation.phantom import make_vessel_phantom


def _obj_with_duplicates(mesh) -> tuple[bytes, np.ndarray]:
    """The mesh written with every face's vertices repeated (as exporters without shared vertices do)."""
    corners = mesh.vertices[mesh.faces].reshape(-1, 3)
    lines = [f"v {x:.6f} {y:.6f} {z:.6f}" for x, y, z in corners[::-1]]  # reversed: order must come from the file
    count = len(corners)
    faces = np.arange(count).reshape(-1, 3)[:, ::-1][::-1]
    lines += [f"f {count - a} {count - b} {count - c}" for a, b, c in faces]
    return ("\n".join(lines) + "\n").encode(), corners[::-1]


def test_obj_vertices_in_file_order_with_duplicates_map_to_their_working_vertex():
    mesh = make_vessel_phantom(seed=2, depth=1)
    data, corners = _obj_with_duplicates(mesh)
    given = vertices_as_given(data, "obj")
    np.testing.assert_allclose(given, corners, atol=1e-6)
    working = read_mesh(data, "model.obj")
    assert len(working.vertices) < len(given)  # the reader merged the duplicates
    moved = transfer(given, working)
    assert moved.distance_mm.max() < 1e-5
    values = np.arange(len(working.vertices), dtype=float)
    per_file = moved.apply(values)
    np.testing.assert_allclose(working.vertices[per_file.astype(int)], given, atol=1e-5)


def test_vessel_points_lie_on_the_phantom_axis():
    mesh = make_vessel_phantom(seed=0, depth=0, n_sides=16)  # one tube: trunk radius 2.2 → 1.87 mm
    points = vessel_points(mesh)
    ring = slice(16 * 4, 16 * 5)  # the fifth ring: its centre is the axis there
    centre = mesh.vertices[ring].mean(axis=0)
    assert np.linalg.norm(points.centres_mm[ring] - centre, axis=1).max() < 0.35
    assert 1.7 < np.median(points.radii_mm) < 2.4


def test_file_vertices_follow_the_unit_read_and_a_volume_uses_the_written_mesh():
    from types import SimpleNamespace

    from dsareg_engine.hemodynamics.run import file_vertices
    from dsareg_engine.io.input_decisions import InputDecision

    mesh = make_vessel_phantom(seed=2, depth=1)
    data, corners = _obj_with_duplicates(_in_cm(mesh))
    case = SimpleNamespace(kinds={"mesh": "obj"}, mesh=mesh,
                           decisions=[InputDecision("mesh", "units", "cm", "the model's largest extent in mm")])
    given, order = file_vertices(SimpleNamespace(mesh=data), case)
    np.testing.assert_allclose(given, corners * 10.0, atol=1e-4)  # the file in cm, the values in mm
    assert "OBJ vertex order" in order
    from_volume, order = file_vertices(SimpleNamespace(mesh=None), SimpleNamespace(kinds={"volume": "nifti"}, mesh=mesh))
    assert from_volume is mesh.vertices and "hemodynamics.ply" in order


def _in_cm(mesh):
    """The same mesh with its coordinates in centimetres."""
    from dsareg_engine.mesh import TriangleMesh

    return TriangleMesh(mesh.vertices / 10.0, mesh.faces)
