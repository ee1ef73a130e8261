"""The points hemodynamics measures: vessel centres behind the model's vertices, and the model file's own vertex order.

**Vessel points.** Each vertex of the working mesh lies on a vessel wall; the vessel it belongs to has its
axis half a local diameter inward along the vertex normal. ``centres_mm`` ``(N, 3)`` are those axis
points and ``radii_mm`` ``(N,)`` the local radius (:func:`local_radii_mm`: half the diameter straight across,
:func:`dsareg_engine.geometry.vessel_tree.vessel_thickness_mm`, as a median over the nearest vertices): a
time–density curve is taken over the vessel's projected cross-section around the centre.

**The file's vertex order.** Outputs are per vertex of the model file *as given*: OBJ ``v`` lines in order,
duplicates included; PLY / OFF / VTP / legacy VTK vertices in order; STL three vertices per triangle. The working mesh merged
duplicates and may be decimated, so each file vertex takes the values of its nearest working vertex
(``transfer``; the distance is reported).
"""

from __future__ import annotations

import io
import re
import warnings
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from ..geometry.vessel_tree import vertex_normals, vessel_thickness_mm
from ..mesh import TriangleMesh

MIN_RADIUS_MM = 0.3
RADIUS_NEIGHBOURS = 12


@dataclass(frozen=True)
class VesselPoints:
    """Vessel axis points behind the working mesh's vertices: ``centres_mm`` ``(N, 3)`` and ``radii_mm`` ``(N,)``,
    mesh frame."""

    centres_mm: np.ndarray
    radii_mm: np.ndarray

    def __len__(self) -> int:
        return len(self.radii_mm)


def local_radii_mm(mesh: TriangleMesh) -> np.ndarray:
    """``(V,)`` the local vessel radius: half the diameter straight across each vertex, then the median over the
    ``RADIUS_NEIGHBOURS`` nearest vertices where one was found (a coarse ring, a bifurcation or a cap can leave a
    vertex without a vertex straight across, or with one on another vessel)."""
    diameter = vessel_thickness_mm(mesh, unfound="nan")
    if not np.isfinite(diameter).any():
        return np.full(len(mesh.vertices), 1.0)
    _, near = cKDTree(mesh.vertices).query(mesh.vertices, k=min(RADIUS_NEIGHBOURS, len(mesh.vertices)))
    with warnings.catch_warnings():  # a vertex none of whose neighbours found a diameter: the overall median
        warnings.simplefilter("ignore", RuntimeWarning)
        local = np.nanmedian(diameter[near], axis=1)
    local = np.where(np.isfinite(local), local, np.nanmedian(diameter))
    return np.maximum(local / 2.0, MIN_RADIUS_MM)


def vessel_points(mesh: TriangleMesh) -> VesselPoints:
    """One vessel point per vertex of ``mesh``: the vertex moved the local radius along its inward normal."""
    radii = local_radii_mm(mesh)
    centres = mesh.vertices - vertex_normals(mesh) * radii[:, None]
    return VesselPoints(centres, radii)


_OBJ_VERTEX = re.compile(rb"(?m)^[ \t]*v[ \t]+(\S+)[ \t]+(\S+)[ \t]+(\S+)")


def vertices_as_given(data: bytes, fmt: str) -> np.ndarray:
    """The model file's vertices ``(V, 3)`` in file order, duplicates included (see the module docstring)."""
    if fmt == "obj":
        rows = _OBJ_VERTEX.findall(data)
        return np.array([[float(x) for x in row] for row in rows], dtype=np.float64).reshape(-1, 3)
    if fmt in ("vtp", "vtk"):  # VTK's points in file order (the triangulation keeps them)
        from ..io.vtk_polydata import parse_vtk_polydata

        return parse_vtk_polydata(data, fmt)[0]
    import trimesh

    loaded = trimesh.load(file_obj=io.BytesIO(data), file_type=fmt, force="mesh", process=False, resolver=None)
    if fmt == "stl":
        return np.asarray(loaded.vertices, np.float64)[np.asarray(loaded.faces)].reshape(-1, 3)
    return np.asarray(loaded.vertices, np.float64)


@dataclass(frozen=True)
class Transfer:
    """File vertex → working vertex: ``index`` ``(V,)`` and the distance ``distance_mm`` ``(V,)``."""

    index: np.ndarray
    distance_mm: np.ndarray

    def apply(self, values: np.ndarray) -> np.ndarray:
        """Per-working-vertex ``values`` ``(N, ...)`` → per file vertex ``(V, ...)``."""
        return values[self.index]


def transfer(file_vertices_mm: np.ndarray, mesh: TriangleMesh) -> Transfer:
    """Each file vertex's nearest working vertex."""
    distance, index = cKDTree(mesh.vertices).query(file_vertices_mm)
    return Transfer(np.asarray(index, np.int64), np.asarray(distance, float))
