"""A picture of the coloured model (what ``hemodynamics.ply`` shows in a 3D viewer), for people and the docs.

Faces are painted far to near (painter's algorithm) in a view at the registered pose, each in the mean colour
of its vertices, shaded by how squarely it faces the viewer; the colour bar of :mod:`.parametric` on the right.
"""

from __future__ import annotations

import cv2
import numpy as np

from ..geometry.rig import ViewGeometry
from ..mesh import TriangleMesh
from .colours import TimeScale
from .parametric import colour_bar

MARGIN_PX = 16


def model_picture(mesh: TriangleMesh, arrival_s: np.ndarray, view: ViewGeometry, mesh_to_world: np.ndarray,
                  scale: TimeScale, title: str, side_px: int = 480) -> np.ndarray:
    """``(H, W, 3)`` BGR: ``mesh`` coloured by ``arrival_s`` ``(V,)``, cropped to the model, with a colour bar."""
    mesh_to_view = view.world_to_view @ np.asarray(mesh_to_world, float)
    points = mesh.vertices @ mesh_to_view[:3, :3].T + mesh_to_view[:3, 3]
    uv = points[:, :2] / points[:, 2:3]
    low, high = uv.min(axis=0), uv.max(axis=0)
    zoom = (side_px - 2 * MARGIN_PX) / max(float((high - low).max()), 1e-9)
    pixels = (uv - low) * zoom + MARGIN_PX
    height, width = (np.ceil((high - low) * zoom).astype(int) + 2 * MARGIN_PX)[::-1]
    canvas = np.full((max(height, 160), width, 3), 24, np.uint8)
    triangles = points[mesh.faces]
    normals = np.cross(triangles[:, 1] - triangles[:, 0], triangles[:, 2] - triangles[:, 0])
    facing = np.abs(normals[:, 2]) / np.maximum(np.linalg.norm(normals, axis=1), 1e-12)
    colours = scale.rgb(arrival_s)[mesh.faces].mean(axis=1)[:, ::-1] * (0.35 + 0.65 * facing)[:, None]
    for face in np.argsort(-triangles[:, :, 2].mean(axis=1)):
        corners = np.round(pixels[mesh.faces[face]] * 4).astype(np.int32)
        cv2.fillConvexPoly(canvas, corners, tuple(int(c) for c in colours[face]), cv2.LINE_AA, shift=2)
    cv2.putText(canvas, title, (6, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.42, (255, 255, 255), 1, cv2.LINE_AA)
    return np.concatenate([canvas, colour_bar(scale, canvas.shape[0])], axis=1)
