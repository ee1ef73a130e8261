"""Surface models in VTK's formats: XML PolyData (``.vtp``) and legacy VTK POLYDATA (``.vtk``), read by VTK itself.

``.vtp`` is what VMTK, SimVascular, AneuRisk and CFD tools write for a vessel surface; legacy ``.vtk`` polydata is
its older text/binary form. The bytes are parsed in memory (VTK's readers read from a string: nothing touches the
filesystem); polygons and triangle strips are split into triangles by ``vtkTriangleFilter``, and vertices and lines
(a centreline stored beside the surface) are dropped. A legacy file holding a volume (``STRUCTURED_POINTS``) is
not a mesh: :mod:`.volume_formats` reads it. VTK states no length unit: millimetres are assumed, and the model's
size is checked like any other mesh's (:mod:`.mesh_units`).
"""

from __future__ import annotations

import re
from contextlib import contextmanager

import numpy as np

from ..errors import DsaregInputError
from .volume_formats import kept_locale

VTK_MESH_FORMATS = ("vtp", "vtk")
LEGACY_MAGIC = b"# vtk DataFile Version"
_LEGACY_DATASET = re.compile(rb"(?m)^\s*DATASET\s+(\w+)")


def legacy_dataset(data: bytes) -> str | None:
    """The ``DATASET`` type (upper case) of a legacy VTK file, or None when ``data`` is not one."""
    if not data.lstrip()[:64].startswith(LEGACY_MAGIC):
        return None
    found = _LEGACY_DATASET.search(data[:4096])
    return found.group(1).decode("ascii", "replace").upper() if found else ""


def detect_vtk_polydata(data: bytes) -> str | None:
    """``"vtp"`` (XML PolyData), ``"vtk"`` (legacy POLYDATA) or None."""
    head = data[:4096]
    if head.lstrip()[:5] in (b"<?xml", b"<VTKF") and re.search(rb"<VTKFile[^>]*type\s*=\s*\"PolyData\"", head):
        return "vtp"
    if legacy_dataset(data) == "POLYDATA":
        return "vtk"
    return None


def declared_triangles(data: bytes, fmt: str) -> int | None:
    """The triangles the header declares, before parsing (at least that many; checked against the face ceiling).
    Legacy: a ``POLYGONS n size`` or ``TRIANGLE_STRIPS n size`` section makes ``size − 3n`` triangles. XML: the
    pieces' ``NumberOfPolys`` + ``NumberOfStrips`` (a polygon makes at least one)."""
    if fmt == "vtk":
        sections = re.findall(rb"(?m)^\s*(?:POLYGONS|TRIANGLE_STRIPS)\s+(\d+)\s+(\d+)", data[: 1 << 26])
        return sum(max(int(size) - 3 * int(n), 0) for n, size in sections) if sections else None
    counts = re.findall(rb"NumberOf(?:Polys|Strips)\s*=\s*\"(\d+)\"", data[: 1 << 20])
    return sum(int(c) for c in counts) if counts else None


@contextmanager
def _vtk_errors(algorithm):
    """VTK's error messages for ``algorithm`` collected (not printed); yields the list they land in."""
    from vtkmodules.vtkCommonCore import vtkCommand, vtkObject

    messages: list[str] = []
    shown = vtkObject.GetGlobalWarningDisplay()
    vtkObject.GlobalWarningDisplayOff()
    tag = algorithm.AddObserver(vtkCommand.ErrorEvent, lambda _obj, _event, *rest: messages.append(
        str(rest[0]) if rest else "error"))
    try:
        yield messages
    finally:
        algorithm.RemoveObserver(tag)
        vtkObject.SetGlobalWarningDisplay(shown)


def _reader(data: bytes, fmt: str):
    if fmt == "vtp":
        from vtkmodules.vtkIOXML import vtkXMLPolyDataReader

        reader = vtkXMLPolyDataReader()
        reader.ReadFromInputStringOn()
        reader.SetInputString(data)
        return reader
    from vtkmodules.vtkIOLegacy import vtkPolyDataReader

    reader = vtkPolyDataReader()
    reader.ReadFromInputStringOn()
    reader.SetBinaryInputString(data, len(data))
    return reader


def parse_vtk_polydata(data: bytes, fmt: str, field_name: str = "mesh") -> tuple[np.ndarray, np.ndarray]:
    """``(vertices (N, 3) float64, faces (M, 3) int64)`` of a ``.vtp`` / legacy ``.vtk`` surface, triangulated.

    Raises:
        DsaregInputError: VTK could not parse it, or it holds no surface (only points or lines).
    """
    from vtkmodules.util.numpy_support import vtk_to_numpy
    from vtkmodules.vtkFiltersCore import vtkTriangleFilter

    name = {"vtp": "VTP (VTK XML PolyData)", "vtk": "legacy VTK POLYDATA"}[fmt]
    reader = _reader(data, fmt)
    triangles = vtkTriangleFilter()
    triangles.SetInputConnection(reader.GetOutputPort())
    triangles.PassVertsOff()
    triangles.PassLinesOff()
    with _vtk_errors(reader) as messages, _vtk_errors(triangles) as more, kept_locale():
        triangles.Update()
    failure = reader.GetErrorCode() != 0 or messages or more
    output = triangles.GetOutput()
    if failure or output.GetPoints() is None:
        detail = (messages + more + ["no points in it"])[0].strip().splitlines()[-1][:200]
        raise DsaregInputError(f"could not be parsed as {name} ({detail})", field=field_name,
                               accepted="a surface mesh (.vtp or legacy .vtk POLYDATA with polygons or strips)")
    vertices = np.asarray(vtk_to_numpy(output.GetPoints().GetData()), dtype=np.float64).reshape(-1, 3)
    polys = output.GetPolys()
    offsets = np.asarray(vtk_to_numpy(polys.GetOffsetsArray()), dtype=np.int64)
    connectivity = np.asarray(vtk_to_numpy(polys.GetConnectivityArray()), dtype=np.int64)
    if len(offsets) < 2:
        raise DsaregInputError(f"the {name} file has no surface (no polygons or strips; lines and points are "
                               "not a surface)", field=field_name,
                               accepted="a surface mesh (.vtp or legacy .vtk POLYDATA with polygons or strips)")
    if np.any(np.diff(offsets) != 3):  # vtkTriangleFilter leaves only triangles; anything else is a reader fault
        raise DsaregInputError(f"the {name} surface could not be split into triangles", field=field_name)
    return vertices, connectivity.reshape(-1, 3)


__all__ = ["VTK_MESH_FORMATS", "declared_triangles", "detect_vtk_polydata", "legacy_dataset", "parse_vtk_polydata"]
