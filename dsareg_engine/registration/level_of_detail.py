"""Level of detail: the faces an Adam stage renders (about ``LOD_FACE_AREA_PX`` px² per projected face), and the
decimated meshes remembered across registrations of the same mesh."""

from __future__ import annotations

import hashlib
import math

import numpy as np

from ..mesh import TriangleMesh, decimate

LOD_MIN_FACES = 1500
LOD_FACE_AREA_PX = 2.0
LOD_STEPS_PER_DOUBLING = 8


def level_of_detail_faces(n_faces: int, mean_face_area_px: float) -> int:
    """Faces to keep so the mean projected face covers about ``LOD_FACE_AREA_PX`` px² (≥ LOD_MIN_FACES).

    Rounded to steps of 2^(1/8) (~9 %) above LOD_MIN_FACES, so registrations of one mesh at nearby
    poses (tracking: every frame) ask for the same level of detail and find it remembered (measured:
    2845, 2888 and 2896 faces on three consecutive frames, each a ~15 ms decimation).
    """
    wanted = max(LOD_MIN_FACES, n_faces * mean_face_area_px / LOD_FACE_AREA_PX)
    steps = round(LOD_STEPS_PER_DOUBLING * math.log2(wanted / LOD_MIN_FACES))
    return int(min(n_faces, round(LOD_MIN_FACES * 2 ** (steps / LOD_STEPS_PER_DOUBLING))))


def mean_projected_face_area_px(mesh: TriangleMesh, view, mesh_to_world: np.ndarray) -> float:
    """Mean area (px², full resolution) of the mesh's faces projected into ``view``."""
    pixels = view.project(mesh.vertices @ mesh_to_world[:3, :3].T + mesh_to_world[:3, 3])
    a, b, c = (pixels[mesh.faces[:, k]] for k in range(3))
    e1, e2 = b - a, c - a
    return float(np.abs(e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]).mean() / 2.0)


_LOD_CACHE: dict[tuple[str, int], TriangleMesh] = {}
_LOD_CACHE_SIZE = 8


def _decimated(mesh: TriangleMesh, faces: int) -> TriangleMesh:
    """``decimate(mesh, faces)``, remembered across registrations of the same mesh (tracking
    re-registers one model frame after frame; decimation cost ~35 ms per level of detail)."""
    digest = hashlib.sha1(np.ascontiguousarray(mesh.vertices).tobytes() + np.ascontiguousarray(mesh.faces).tobytes()).hexdigest()
    key = (digest, faces)
    if key not in _LOD_CACHE:
        if len(_LOD_CACHE) >= _LOD_CACHE_SIZE:
            _LOD_CACHE.pop(next(iter(_LOD_CACHE)))
        _LOD_CACHE[key] = decimate(mesh, faces)
    return _LOD_CACHE[key]
