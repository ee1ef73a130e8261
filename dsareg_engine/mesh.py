"""Triangle mesh container (mesh frame, millimetres)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch


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

    def torch(self, dtype: torch.dtype = torch.float32, device: str | torch.device = "cpu") -> tuple[torch.Tensor, torch.Tensor]:
        """``(vertices (V, 3), faces (F, 3) int64)`` as tensors."""
        return (
            torch.as_tensor(self.vertices, dtype=dtype, device=device),
            torch.as_tensor(self.faces, dtype=torch.int64, device=device),
        )

    def transformed(self, transform: np.ndarray) -> "TriangleMesh":
        """The mesh with a 4x4 transform applied to its vertices."""
        vertices = self.vertices @ transform[:3, :3].T + transform[:3, 3]
        return TriangleMesh(vertices, self.faces)

    def save(self, path: str | Path) -> None:
        """Write OBJ/STL/PLY (by extension) with trimesh."""
        import trimesh

        trimesh.Trimesh(self.vertices, self.faces, process=False).export(str(path))
