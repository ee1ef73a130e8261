"""A vessel model read as a tree: geodesic distances along its surface, its inflow, what lies downstream.

Nodes are the mesh's vertices, edges its face edges (length-weighted). Models built from tubes
that overlap without sharing vertices (the built-in phantom, meshes joined from parts) fall
apart into pieces; each piece is bridged to its nearest other piece until one graph remains,
so a distance runs from the inflow through every branch. Distances are mm along the surface.

Used to pick a part of a model (:func:`select_region`: the faces to register with when the
user says what was injected) and by the partial-filling simulations
(:mod:`dsareg_engine.simulation.partial_filling`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import sparse
from scipy.sparse import csgraph
from scipy.spatial import cKDTree

from ..mesh import TriangleMesh

DOWNSTREAM_TOLERANCE_DIAMETERS = 2.0
"""A vertex lies downstream of a point when its shortest path from the inflow passes within this many
local vessel diameters of the point (paths run around a tube's wall, not along its axis)."""
DOWNSTREAM_BATCH = 32
"""Points per Dijkstra of :meth:`VesselTree.downstream_sets` (each batch stops at its farthest point's reach)."""


@dataclass(frozen=True)
class VesselTree:
    """The surface graph of a mesh ``(V vertices)``: ``graph`` (V, V) sparse, ``thickness_mm`` (V,)
    local vessel diameter estimate, ``inflow`` the vertex index where contrast enters."""

    mesh: TriangleMesh
    graph: sparse.csr_matrix
    thickness_mm: np.ndarray
    inflow: int

    def distances_from(self, vertex: int) -> np.ndarray:
        """Geodesic distance (mm, ``(V,)``) from ``vertex`` along the surface graph."""
        return csgraph.dijkstra(self.graph, directed=False, indices=vertex)

    def downstream_of(self, vertex: int) -> np.ndarray:
        """``(V,)`` bool: vertices whose path from the inflow runs through ``vertex`` (its branch, and beyond)."""
        from_inflow = self.distances_from(self.inflow)
        from_point = self.distances_from(vertex)
        tolerance = DOWNSTREAM_TOLERANCE_DIAMETERS * max(float(self.thickness_mm[vertex]), 0.5)
        return (from_inflow[vertex] + from_point <= from_inflow + tolerance) & (from_inflow >= from_inflow[vertex] - tolerance)

    def downstream_sets(self, vertices: np.ndarray, batch: int = DOWNSTREAM_BATCH) -> np.ndarray:
        """``(K, V)`` bool: :meth:`downstream_of` for each of ``vertices`` ``(K,)`` (batched Dijkstras).

        A vertex ``v`` is downstream of point ``p`` only if ``d(p, v) ≤ d(inflow, v) + tol − d(inflow, p)``, at most
        the farthest inflow distance less ``p``'s own plus ``tol``: each Dijkstra stops there (the ``limit`` of its
        batch, points of similar reach batched together), so a point far down the tree explores its own subtree and
        not the whole model. Distances within the limit are the unlimited ones: the sets are the same."""
        vertices = np.asarray(vertices, dtype=np.int64)
        from_inflow = self.distances_from(self.inflow)
        start = from_inflow[vertices]
        tolerance = DOWNSTREAM_TOLERANCE_DIAMETERS * np.maximum(self.thickness_mm[vertices], 0.5)
        reach = from_inflow.max() + tolerance - start
        sets = np.zeros((len(vertices), len(from_inflow)), bool)
        order = np.argsort(reach, kind="stable")
        for first in range(0, len(order), batch):
            rows = order[first: first + batch]
            limit = float(reach[rows].max()) * (1.0 + 1e-9) + 1e-9  # a vertex exactly at the bound stays in
            from_points = csgraph.dijkstra(self.graph, directed=False, indices=vertices[rows], limit=limit)
            sets[rows] = ((start[rows, None] + from_points <= from_inflow[None] + tolerance[rows, None])
                          & (from_inflow[None] >= start[rows, None] - tolerance[rows, None]))
        return sets


def vessel_tree(mesh: TriangleMesh, inflow_mm: np.ndarray | None = None) -> VesselTree:
    """Build the tree of ``mesh``; ``inflow_mm`` (mesh mm) picks the inflow, else :func:`guess_inflow`."""
    graph = _surface_graph(mesh)
    thickness = vessel_thickness_mm(mesh)
    inflow = (int(cKDTree(mesh.vertices).query(inflow_mm)[1]) if inflow_mm is not None
              else guess_inflow(mesh, thickness))
    return VesselTree(mesh, graph, thickness, inflow)


def guess_inflow(mesh: TriangleMesh, thickness_mm: np.ndarray) -> int:
    """The vertex where contrast most likely enters: on the thickest vessel (within 90 % of the
    95th-percentile diameter), the one farthest from the model's centre (an arterial tree narrows
    from its feeding trunk outward, and the trunk enters from the model's edge)."""
    thick = thickness_mm >= 0.9 * np.percentile(thickness_mm, 95)
    candidates = np.flatnonzero(thick)
    far = np.linalg.norm(mesh.vertices[candidates] - mesh.centroid, axis=1)
    return int(candidates[np.argmax(far)])


def vessel_thickness_mm(mesh: TriangleMesh, neighbours: int = 96, *, unfound: str = "median") -> np.ndarray:
    """Local vessel diameter at each vertex ``(V,)``: distance to the nearest vertex straight across,
    along the inward normal (within 25°; the vertex's ``neighbours`` nearest are searched). Where none is found:
    the median of the others (``unfound="median"``) or NaN (``"nan"``)."""
    normals = vertex_normals(mesh)
    count = min(neighbours, len(mesh.vertices))
    distance, index = cKDTree(mesh.vertices).query(mesh.vertices, k=count)
    offsets = mesh.vertices[index] - mesh.vertices[:, None, :]
    along = -(offsets @ normals[:, :, None])[..., 0]
    across = along > np.cos(np.radians(25.0)) * np.maximum(distance, 1e-9)
    diameter = np.where(across, distance, np.inf).min(axis=1)
    finite = np.isfinite(diameter)
    if unfound == "nan":
        return np.where(finite, diameter, np.nan)
    fallback = float(np.median(diameter[finite])) if finite.any() else 1.0
    return np.where(finite, diameter, fallback)


def vertex_normals(mesh: TriangleMesh) -> np.ndarray:
    """Area-weighted outward vertex normals ``(V, 3)`` (unit; faces wound outward)."""
    a, b, c = (mesh.vertices[mesh.faces[:, k]] for k in range(3))
    face_normals = np.cross(b - a, c - a)
    normals = np.zeros_like(mesh.vertices)
    for k in range(3):
        np.add.at(normals, mesh.faces[:, k], face_normals)
    return normals / np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)


def _surface_graph(mesh: TriangleMesh) -> sparse.csr_matrix:
    """Face edges weighted by length, with each disconnected piece bridged to its nearest other piece."""
    faces = mesh.faces
    edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    count = len(mesh.vertices)
    rows, cols = list(edges[:, 0]), list(edges[:, 1])
    graph = _graph(mesh.vertices, rows, cols, count)
    pieces, labels = csgraph.connected_components(graph, directed=False)
    while pieces > 1:
        for piece in range(pieces):
            inside = np.flatnonzero(labels == piece)
            outside = np.flatnonzero(labels != piece)
            distance, nearest = cKDTree(mesh.vertices[outside]).query(mesh.vertices[inside])
            best = int(np.argmin(distance))
            rows.append(int(inside[best]))
            cols.append(int(outside[nearest[best]]))
        graph = _graph(mesh.vertices, rows, cols, count)
        pieces, labels = csgraph.connected_components(graph, directed=False)
    return graph


def _graph(vertices: np.ndarray, rows: list, cols: list, count: int) -> sparse.csr_matrix:
    rows_array, cols_array = np.asarray(rows), np.asarray(cols)
    lengths = np.maximum(np.linalg.norm(vertices[rows_array] - vertices[cols_array], axis=1), 1e-6)
    return sparse.coo_matrix((lengths, (rows_array, cols_array)), shape=(count, count)).tocsr()


def faces_of(mesh: TriangleMesh, vertex_mask: np.ndarray) -> TriangleMesh:
    """The sub-mesh of the faces whose three vertices are in ``vertex_mask`` ``(V,)`` bool, vertices compacted."""
    keep = vertex_mask[mesh.faces].all(axis=1)
    return compact(mesh, keep)


def compact(mesh: TriangleMesh, face_mask: np.ndarray) -> TriangleMesh:
    """The sub-mesh of the faces in ``face_mask`` ``(F,)`` bool, unused vertices dropped."""
    faces = mesh.faces[face_mask]
    used, inverse = np.unique(faces, return_inverse=True)
    return TriangleMesh(mesh.vertices[used], inverse.reshape(faces.shape).astype(np.int64))


MIN_REGION_FACES = 50


def select_region(mesh: TriangleMesh, region) -> TriangleMesh:
    """The faces of ``mesh`` inside ``region`` (:class:`~dsareg_engine.registration.options.ModelRegion`):
    all three vertices in the box / sphere, or downstream of the vertex nearest ``branch_near_mm``."""
    from ..errors import DsaregInputError

    vertices = mesh.vertices
    if region.box_mm is not None:
        low, high = np.minimum(*np.asarray(region.box_mm)), np.maximum(*np.asarray(region.box_mm))
        inside = np.all((vertices >= low) & (vertices <= high), axis=1)
        field = "options.region.box_mm"
    elif region.sphere is not None:
        centre, radius = np.asarray(region.sphere.centre_mm), float(region.sphere.radius_mm)
        inside = np.linalg.norm(vertices - centre, axis=1) <= radius
        field = "options.region.sphere"
    else:
        tree = vessel_tree(mesh)
        inside = tree.downstream_of(int(cKDTree(vertices).query(np.asarray(region.branch_near_mm))[1]))
        field = "options.region.branch_near_mm"
    selected = faces_of(mesh, inside)
    if selected.n_faces < MIN_REGION_FACES:
        raise DsaregInputError(
            f"selects {selected.n_faces} of the model's {mesh.n_faces} faces", field=field,
            accepted=f"a region (model frame, mm) holding at least {MIN_REGION_FACES} faces of the model")
    return selected
