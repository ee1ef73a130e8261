"""Differentiable silhouette rendering: camera → rasterizer → shader."""

from .camera import Camera, project_triangles, transform_points
from .settings import SilhouetteSettings
from .silhouette import (
    SilhouetteRenderer,
    numba_available,
    render_hard_silhouette,
    render_soft_silhouette,
)

__all__ = [
    "Camera",
    "SilhouetteRenderer",
    "SilhouetteSettings",
    "numba_available",
    "project_triangles",
    "render_hard_silhouette",
    "render_soft_silhouette",
    "transform_points",
]
