"""Triangle mesh container (mesh frame, millimetres), its clean-up from raw arrays and decimation.

Decimation uses quadric error simplification (fast-simplification), which keeps thin tubes: its
error metric weighs distance to the original surface, so a thin vessel is never collapsed while
flat, well-sampled regions can absorb the reduction. Where that package is missing, vertex
clustering on a fine grid is used instead.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from .errors import DsaregInputError

if TYPE_CHECKING:  # torch is imported where it is used: parsing inputs (the API's validator) needs none
    import torch

log = logging.getLogger(__name__)

MESH_FILES_ACCEPTED = "OBJ, STL (ASCII or binary), PLY, OFF, GLB, VTP or legacy VTK polydata"


@dataclass(frozen=True)
class TriangleMesh:
    """Vertices ``(V, 3)`` float64 mm in the mesh frame and faces ``(F, 3)`` int64."""

    vertices: np.ndarray
    faces: np.ndarray

    @property
    def n_faces(self) -> int:
        return int(self.faces.shape[0])

    @property
    def centroid(self) -> np.ndarray:
        """Mean of the vertices, mm ``(3,)``: the centre registration rotates about."""
        return self.vertices.mean(axis=0)

    def torch(self, dtype: torch.dtype | None = None, device: str | torch.device = "cpu"
              ) -> tuple[torch.Tensor, torch.Tensor]:
        """``(vertices (V, 3), faces (F, 3) int64)`` as tensors (``dtype`` float32 unless given)."""
        import torch

        dtype = torch.float32 if dtype is None else dtype
        return (
            torch.as_tensor(self.vertices, dtype=dtype, device=device),
            torch.as_tensor(self.faces, dtype=torch.int64, device=device),
        )

    def transformed(self, transform: np.ndarray) -> TriangleMesh:
        """The mesh with a 4x4 transform applied to its vertices."""
        vertices = self.vertices @ transform[:3, :3].T + transform[:3, 3]
        return TriangleMesh(vertices, self.faces)

    def save(self, path: str | Path) -> None:
        """Write OBJ/STL/PLY (by extension) with trimesh."""
        import trimesh

        trimesh.Trimesh(self.vertices, self.faces, process=False).export(str(path))


def mesh_from_arrays(vertices: np.ndarray, faces: np.ndarray, *, max_faces: int, field_name: str = "mesh") -> TriangleMesh:
    """Check raw arrays and return a clean :class:`TriangleMesh` (duplicate vertices merged, degenerate
    faces and unused vertices dropped); :class:`DsaregInputError` naming ``field_name`` otherwise."""
    vertices = np.asarray(vertices, dtype=np.float64)
    faces = np.asarray(faces)
    if faces.size == 0:
        raise DsaregInputError(
            "has no faces (a point cloud or an empty file?)", field=field_name, accepted="a triangle surface mesh"
        )
    if vertices.ndim != 2 or vertices.shape[1] != 3 or len(vertices) == 0:
        raise DsaregInputError("has no vertices", field=field_name, accepted=MESH_FILES_ACCEPTED)
    if faces.ndim != 2 or faces.shape[1] != 3:
        raise DsaregInputError(f"faces have shape {list(faces.shape)}", field=field_name, accepted="triangles")
    if len(faces) > max_faces:
        raise DsaregInputError(f"has {len(faces)} faces, above the limit of {max_faces}", field=field_name)
    if not np.all(np.isfinite(vertices)):
        bad = int(np.count_nonzero(~np.isfinite(vertices).all(axis=1)))
        raise DsaregInputError(
            f"{bad} vertices have NaN or infinite coordinates", field=field_name, accepted="finite coordinates in mm"
        )
    if not np.issubdtype(faces.dtype, np.integer):
        if not np.all(np.isfinite(faces)) or np.any(faces != np.round(faces)):
            raise DsaregInputError("face indices are not integers", field=field_name)
    faces = faces.astype(np.int64)
    if faces.min() < 0 or faces.max() >= len(vertices):
        raise DsaregInputError(
            f"face indices span [{faces.min()}, {faces.max()}] but there are {len(vertices)} vertices",
            field=field_name,
            accepted="indices in range",
        )
    if np.abs(vertices).max() > 1e6:
        raise DsaregInputError("coordinates exceed 1 km; the mesh must be in millimetres", field=field_name)
    # Merge coincident vertices (STL stores each triangle separately) and drop degenerate faces.
    scale = max(float(np.ptp(vertices, axis=0).max()), 1e-9)
    keys = np.round(vertices / (scale * 1e-9)).astype(np.int64)
    _, first, inverse = np.unique(keys, axis=0, return_index=True, return_inverse=True)
    vertices = vertices[first]
    faces = inverse.reshape(-1)[faces]
    keep = (faces[:, 0] != faces[:, 1]) & (faces[:, 1] != faces[:, 2]) & (faces[:, 0] != faces[:, 2])
    faces = faces[keep]
    if len(faces) == 0:
        raise DsaregInputError("every face is degenerate (zero area)", field=field_name)
    used = np.unique(faces)
    remap = np.full(len(vertices), -1, dtype=np.int64)
    remap[used] = np.arange(len(used))
    return TriangleMesh(np.ascontiguousarray(vertices[used]), remap[faces])


def decimate(mesh: TriangleMesh, target_faces: int) -> TriangleMesh:
    """Reduce ``mesh`` to about ``target_faces`` faces, preserving thin tubes."""
    if mesh.n_faces <= target_faces:
        return mesh
    try:
        import fast_simplification

        reduction = 1.0 - target_faces / mesh.n_faces
        vertices, faces = fast_simplification.simplify(
            mesh.vertices.astype(np.float32), mesh.faces.astype(np.int32), target_reduction=reduction, agg=7
        )
        vertices = np.asarray(vertices, dtype=np.float64)
        faces = np.asarray(faces, dtype=np.int64)
        if len(faces) == 0:
            raise RuntimeError("quadric decimation removed every face")
        return mesh_from_arrays(vertices, faces, max_faces=max(len(faces), 1))
    except ImportError:
        log.info("fast-simplification not installed; decimating by vertex clustering")
    return _cluster_decimate(mesh, target_faces)


def _cluster_decimate(mesh: TriangleMesh, target_faces: int) -> TriangleMesh:
    """Vertex clustering on the finest grid that reaches the budget (bisection on the cell size)."""
    extent = float(np.ptp(mesh.vertices, axis=0).max())
    lo, hi = extent * 1e-4, extent / 4
    best = None
    for _ in range(20):
        cell = np.sqrt(lo * hi)
        keys = np.floor(mesh.vertices / cell).astype(np.int64)
        _, inverse, counts = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
        inverse = inverse.reshape(-1)
        sums = np.zeros((len(counts), 3))
        np.add.at(sums, inverse, mesh.vertices)
        faces = inverse[mesh.faces]
        keep = (faces[:, 0] != faces[:, 1]) & (faces[:, 1] != faces[:, 2]) & (faces[:, 0] != faces[:, 2])
        faces = np.unique(np.sort(faces[keep], axis=1), axis=0, return_index=True)[1]
        faces = inverse[mesh.faces][keep][np.sort(faces)]
        if len(faces) <= target_faces:
            best = (sums / counts[:, None], faces)
            hi = cell
        else:
            lo = cell
        if best is not None and hi / lo < 1.05:
            break
    if best is None:
        return mesh
    return mesh_from_arrays(best[0], best[1], max_faces=max(len(best[1]), 1))
