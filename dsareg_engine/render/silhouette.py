"""Soft and hard silhouettes of a mesh, batched over poses; backend dispatch.

Data flow: mesh vertices ``(V, 3)`` → ``mesh_to_view`` ``(B, 4, 4)`` → projected face
corners ``(B, F, 3, 2)`` px → rasterize (per-pixel face distances) → shade → ``(B, H, W)``.
"""

from __future__ import annotations

import torch

from .boxes import face_pixel_boxes
from .camera import Camera, project_triangles, transform_points
from .rasterize_torch import rasterize_fragments
from .settings import SilhouetteSettings
from .shade import alpha_from_log_keep, hard_from_fragments, soft_log_keep_from_fragments

try:  # numba is a hard dependency, but a broken install must not break rendering
    from . import kernels_numba as _numba

    _SOFTPLUS_TABLE, _SIGMOID_TABLE = _numba.make_tables()
except Exception:  # pragma: no cover - exercised only on broken installs
    _numba = None


def _threads() -> int:
    import numba

    return numba.get_num_threads()


def numba_available() -> bool:
    return _numba is not None


def _use_numba(settings: SilhouetteSettings, tensor: torch.Tensor) -> bool:
    if settings.backend == "torch":
        return False
    if settings.backend == "numba":
        if _numba is None:
            raise RuntimeError("backend='numba' requested but numba could not be imported")
        if tensor.device.type != "cpu":
            raise RuntimeError("backend='numba' runs on CPU tensors only")
        return True
    return _numba is not None and tensor.device.type == "cpu"


class _SoftLogKeepNumba(torch.autograd.Function):
    """``Σ_f log(1 − sigmoid(−d_f/σ))`` per pixel with the fused CPU kernels."""

    @staticmethod
    def forward(ctx, triangles, valid, width, height, sigma, radius):  # type: ignore[override]
        boxes = face_pixel_boxes(triangles, valid, width, height, radius).numpy()
        tris = triangles.detach().contiguous().numpy()
        out = torch.zeros((triangles.shape[0], height, width), dtype=triangles.dtype)
        exact = triangles.dtype == torch.float64  # tables (~2e-6) suffice for float32 work
        _numba.soft_log_keep(tris, boxes, height, width, float(sigma), float(radius), exact, _SOFTPLUS_TABLE, _threads(), out.numpy())
        ctx.save_for_backward(triangles)
        ctx.boxes, ctx.sigma, ctx.radius = boxes, sigma, radius
        return out

    @staticmethod
    def backward(ctx, grad_out):  # type: ignore[override]
        (triangles,) = ctx.saved_tensors
        grad = torch.zeros_like(triangles)
        _numba.soft_log_keep_backward(
            triangles.detach().contiguous().numpy(), ctx.boxes, float(ctx.sigma), float(ctx.radius),
            triangles.dtype == torch.float64, _SIGMOID_TABLE, _threads(), grad_out.contiguous().numpy(), grad.numpy(),
        )
        return grad, None, None, None, None, None


def soft_silhouette_from_triangles(
    triangles: torch.Tensor, valid: torch.Tensor, width: int, height: int, settings: SilhouetteSettings
) -> torch.Tensor:
    """Soft silhouettes ``(B, H, W)`` in [0, 1] from projected faces ``(B, F, 3, 2)`` px."""
    radius = settings.blur_radius_px
    if _use_numba(settings, triangles):
        log_keep = _SoftLogKeepNumba.apply(triangles, valid, width, height, settings.sigma_px, radius)
    else:
        fragments = rasterize_fragments(triangles, valid, width, height, radius)
        log_keep = soft_log_keep_from_fragments(fragments, settings.sigma_px, radius)
    return alpha_from_log_keep(log_keep)


def hard_silhouette_from_triangles(
    triangles: torch.Tensor, valid: torch.Tensor, width: int, height: int, settings: SilhouetteSettings
) -> torch.Tensor:
    """Binary silhouettes ``(B, H, W)`` bool: pixel centres inside (or on) some face."""
    with torch.no_grad():
        if _use_numba(settings, triangles):
            boxes = face_pixel_boxes(triangles, valid, width, height, 0.0).numpy()
            out = torch.zeros((triangles.shape[0], height, width), dtype=torch.bool)
            _numba.coverage(triangles.contiguous().numpy(), boxes, height, width, _threads(), out.numpy())
            return out
        return hard_from_fragments(rasterize_fragments(triangles, valid, width, height, 1e-9))


def render_soft_silhouette(
    vertices: torch.Tensor,
    faces: torch.Tensor,
    mesh_to_view: torch.Tensor,
    camera: Camera,
    settings: SilhouetteSettings = SilhouetteSettings(),
) -> torch.Tensor:
    """Differentiable soft silhouettes of a mesh seen in one view under B poses.

    Args:
        vertices: ``(V, 3)`` mesh-frame mm (or ``(B, V, 3)``).
        faces: ``(F, 3)`` int64.
        mesh_to_view: ``(B, 4, 4)``.
        camera: intrinsics of the view.

    Returns:
        ``(B, H, W)`` in [0, 1], differentiable w.r.t. ``mesh_to_view`` and ``vertices``.
    """
    triangles, valid = project_triangles(transform_points(vertices, mesh_to_view), faces, camera, settings.near_mm)
    return soft_silhouette_from_triangles(triangles, valid, camera.width, camera.height, settings)


def render_hard_silhouette(
    vertices: torch.Tensor,
    faces: torch.Tensor,
    mesh_to_view: torch.Tensor,
    camera: Camera,
    settings: SilhouetteSettings = SilhouetteSettings(),
) -> torch.Tensor:
    """Binary silhouettes ``(B, H, W)`` bool; equals the soft one thresholded at 0.5 as σ → 0."""
    with torch.no_grad():
        triangles, valid = project_triangles(transform_points(vertices, mesh_to_view), faces, camera, settings.near_mm)
    return hard_silhouette_from_triangles(triangles, valid, camera.width, camera.height, settings)


class SilhouetteRenderer(torch.nn.Module):
    """Module wrapper: a fixed mesh and camera, rendering B poses per call.

    Args:
        vertices: ``(V, 3)`` mesh-frame mm.
        faces: ``(F, 3)`` int64.
        camera: intrinsics.
        settings: silhouette settings.
    """

    def __init__(self, vertices: torch.Tensor, faces: torch.Tensor, camera: Camera, settings: SilhouetteSettings = SilhouetteSettings()):
        super().__init__()
        self.register_buffer("vertices", vertices)
        self.register_buffer("faces", faces)
        self.camera = camera
        self.settings = settings

    def forward(self, mesh_to_view: torch.Tensor) -> torch.Tensor:
        """``(B, 4, 4) → (B, H, W)`` soft silhouettes."""
        return render_soft_silhouette(self.vertices, self.faces, mesh_to_view, self.camera, self.settings)

    def hard(self, mesh_to_view: torch.Tensor) -> torch.Tensor:
        """``(B, 4, 4) → (B, H, W)`` bool."""
        return render_hard_silhouette(self.vertices, self.faces, mesh_to_view, self.camera, self.settings)
