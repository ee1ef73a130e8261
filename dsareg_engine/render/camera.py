"""Pinhole intrinsics for rendering, and projection of mesh faces to the image."""

from __future__ import annotations

from dataclasses import dataclass

import torch

from ..geometry.rig import ViewGeometry


@dataclass(frozen=True)
class Camera:
    """Pixel intrinsics of one view (see :mod:`dsareg_engine.geometry.rig` for frames).

    Attributes:
        focal_px: ``(fx, fy) = (sid/du, sid/dv)``.
        principal_point_px: ``(u0, v0)``.
        width, height: image size in pixels.
    """

    focal_px: tuple[float, float]
    principal_point_px: tuple[float, float]
    width: int
    height: int

    @classmethod
    def from_view(cls, view: ViewGeometry) -> "Camera":
        return cls(view.focal_px, view.principal_point_px, view.width, view.height)


def transform_points(points: torch.Tensor, transforms: torch.Tensor) -> torch.Tensor:
    """Apply 4x4 transforms to points.

    Args:
        points: ``(V, 3)`` or ``(B, V, 3)``.
        transforms: ``(B, 4, 4)``.

    Returns:
        ``(B, V, 3)``.
    """
    rotation, translation = transforms[:, :3, :3], transforms[:, :3, 3]
    if points.dim() == 2:
        return torch.einsum("bij,vj->bvi", rotation, points) + translation[:, None, :]
    return torch.einsum("bij,bvj->bvi", rotation, points) + translation[:, None, :]


def project_points(vertices_view: torch.Tensor, camera: Camera, near_mm: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Pinhole projection of view-frame points to pixels.

    Args:
        vertices_view: ``(B, V, 3)`` mm in the view frame.
        camera: intrinsics.
        near_mm: points with view ``z < near_mm`` (on or behind the source) are flagged.

    Returns:
        pixels: ``(B, V, 2)`` ``(u, v)``; finite placeholders where not ok.
        ok: ``(B, V)`` bool, in front of the near limit and finite.
    """
    z = vertices_view[..., 2]
    in_front = z >= near_mm
    safe_z = torch.where(in_front, z, torch.full_like(z, near_mm))
    fx, fy = camera.focal_px
    u0, v0 = camera.principal_point_px
    u = u0 + fx * vertices_view[..., 0] / safe_z
    v = v0 + fy * vertices_view[..., 1] / safe_z
    pixels = torch.stack([u, v], dim=-1)
    return pixels, in_front & torch.isfinite(pixels).all(-1)


def project_triangles(
    vertices_view: torch.Tensor, faces: torch.Tensor, camera: Camera, near_mm: float
) -> tuple[torch.Tensor, torch.Tensor]:
    """Project view-frame vertices and gather them per face.

    Faces with a vertex at view ``z < near_mm`` (on or behind the source) or a
    non-finite coordinate are marked invalid and must be skipped by the rasterizer;
    they are dropped, not clipped.

    Args:
        vertices_view: ``(B, V, 3)`` mm in the view frame.
        faces: ``(F, 3)`` int64 vertex indices.
        camera: intrinsics.
        near_mm: near limit on view z.

    Returns:
        triangles: ``(B, F, 3, 2)`` pixel coordinates ``(u, v)`` of each face's corners.
        valid: ``(B, F)`` bool.
    """
    pixels, vertex_ok = project_points(vertices_view, camera, near_mm)
    # index_select (backward: index_add) is much faster on CPU than advanced indexing
    # (backward: index_put with accumulation).
    triangles = pixels.index_select(1, faces.reshape(-1)).view(pixels.shape[0], faces.shape[0], 3, 2)
    return triangles, vertex_ok[:, faces].all(-1)
