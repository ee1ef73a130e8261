"""VTP and legacy VTK polydata surfaces (VMTK / SimVascular models), made here with VTK's own writers or by hand."""

import numpy as np
import pytest
from scipy.spatial import cKDTree

from dsareg_engine.errors import DsaregInputError
from dsareg_engine.io.limits import InputLimits
from dsareg_engine.io.mesh_io import detect_mesh_format, read_mesh_detailed
from dsareg_engine.io.vtk_polydata import declared_triangles, parse_vtk_polydata
from dsareg_engine.simulation.phantom import make_vessel_phantom


@pytest.fixture(scope="module")
def phantom():
    return make_vessel_phantom(depth=2)


def _polydata(mesh):
    from vtkmodules.util.numpy_support import numpy_to_vtk, numpy_to_vtkIdTypeArray
    from vtkmodules.vtkCommonCore import vtkPoints
    from vtkmodules.vtkCommonDataModel import vtkCellArray, vtkPolyData

    points = vtkPoints()
    points.SetData(numpy_to_vtk(np.ascontiguousarray(mesh.vertices, np.float32), deep=True))
    cells = vtkCellArray()
    offsets = np.arange(0, 3 * mesh.n_faces + 1, 3, dtype=np.int64)
    cells.SetData(numpy_to_vtkIdTypeArray(offsets, deep=True),
                  numpy_to_vtkIdTypeArray(np.ascontiguousarray(mesh.faces.ravel(), np.int64), deep=True))
    polydata = vtkPolyData()
    polydata.SetPoints(points)
    polydata.SetPolys(cells)
    return polydata


def _vtp(mesh, mode: str = "appended") -> bytes:
    from vtkmodules.vtkIOXML import vtkXMLPolyDataWriter

    writer = vtkXMLPolyDataWriter()
    writer.SetInputData(_polydata(mesh))
    writer.WriteToOutputStringOn()
    {"appended": writer.SetDataModeToAppended, "binary": writer.SetDataModeToBinary,
     "ascii": writer.SetDataModeToAscii}[mode]()
    writer.Write()
    text = writer.GetOutputString()
    return text.encode("latin-1") if isinstance(text, str) else bytes(text)


@pytest.mark.parametrize("mode", ["appended", "binary", "ascii"])
def test_vtp_round_trip_keeps_the_surface(phantom, mode):
    data = _vtp(phantom, mode)
    assert detect_mesh_format(data) == "vtp"
    result = read_mesh_detailed(data, "model.vtp")
    assert result.format == "vtp" and not result.warnings and result.mesh.n_faces == phantom.n_faces
    assert cKDTree(result.mesh.vertices).query(phantom.vertices)[0].max() < 1e-3  # float32 in the file, mm kept


LEGACY = b"""# vtk DataFile Version 3.0
a square, a quad and a strip
ASCII
DATASET POLYDATA
POINTS 8 float
0 0 0  20 0 0  20 20 0  0 20 0
0 0 20  20 0 20  20 20 20  0 20 20
LINES 1 3
2 0 6
POLYGONS 2 9
4 0 1 2 3
3 4 5 6
TRIANGLE_STRIPS 1 5
4 0 4 1 5
"""


def test_legacy_polydata_polygons_and_strips_are_triangulated():
    assert detect_mesh_format(LEGACY) == "vtk"
    assert declared_triangles(LEGACY, "vtk") == 3 + 2  # quad 2 + triangle 1, strip of 4 points 2
    vertices, faces = parse_vtk_polydata(LEGACY, "vtk")
    assert faces.shape == (5, 3) and vertices.shape == (8, 3)  # the line is dropped
    result = read_mesh_detailed(LEGACY, "model.vtk")
    assert result.format == "vtk" and result.mesh.n_faces == 5


def test_legacy_volume_given_as_a_mesh_is_named():
    volume = b"# vtk DataFile Version 3.0\nx\nASCII\nDATASET STRUCTURED_POINTS\nDIMENSIONS 2 2 2\n"
    with pytest.raises(DsaregInputError, match="STRUCTURED_POINTS file, not a surface"):
        read_mesh_detailed(volume, "carotid.vtk")


@pytest.mark.parametrize("data, match", [
    (b'<?xml version="1.0"?>\n<VTKFile type="PolyData"><PolyData><Piece NumberOfPoints="3"', "could not be parsed"),
    (b"# vtk DataFile Version 3.0\nx\nASCII\nDATASET POLYDATA\nPOINTS 2 float\n0 0 0 1 1 1\nLINES 1 3\n2 0 1\n",
     "no surface"),
])
def test_broken_or_surface_less_files_are_refused(data, match):
    with pytest.raises(DsaregInputError, match=match):
        read_mesh_detailed(data, "model.vtp")


def test_face_ceiling_checked_from_the_header(phantom):
    with pytest.raises(DsaregInputError, match="declares"):
        read_mesh_detailed(_vtp(phantom), "model.vtp", limits=InputLimits(max_faces=100, working_faces=50))


def test_hemodynamics_follows_the_vtk_files_own_vertices():
    from dsareg_engine.hemodynamics.model_points import vertices_as_given

    vertices = vertices_as_given(LEGACY, "vtk")  # per-vertex outputs follow the file's points, in order
    assert vertices.shape == (8, 3) and np.allclose(vertices[6], [20.0, 20.0, 20.0])
