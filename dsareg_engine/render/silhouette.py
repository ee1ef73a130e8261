"""Soft and hard silhouettes of a mesh, batched over poses; backend dispatch.

Data flow: mesh vertices ``(V, 3)`` → ``mesh_to_view`` ``(B, 4, 4)`` → projected vertices
``(B, V, 2)`` px → face corners ``(B, F, 3, 2)`` → rasterize (per-pixel face distances) →
shade → ``(B, H, W)``. The numba back end fuses the last three steps.
"""

from __future__ import annotations

import numpy as np
import torch

from .camera import Camera, project_points, project_triangles, transform_points
from .rasterize_torch import rasterize_fragments
from .settings import SilhouetteSettings
from .shade import alpha_from_log_keep, hard_from_fragments, soft_log_keep_from_fragments

try:  # numba is a hard dependency, but a broken install must not break rendering
    from . import kernels_numba as _numba
    from .serial_kernels import KernelPair

    _SOFTPLUS_TABLE, _SIGMOID_TABLE = _numba.make_tables()
    _KERNELS = {name: KernelPair(getattr(_numba, name)) for name in
                ("gather_faces", "scatter_to_vertices", "soft_log_keep", "soft_log_keep_backward", "coverage")}
except Exception:  # pragma: no cover - exercised only on broken installs
    _numba = None


def _threads() -> int:
    import numba

    return numba.get_num_threads()


def _kernel(name: str) -> tuple:
    """(the numba kernel ``name`` for this thread's budget: its serial twin on 1 thread, the thread count)."""
    n_threads = _threads()
    return _KERNELS[name].pick(n_threads), n_threads


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


def _gather_faces(pixels: torch.Tensor, vertex_ok: torch.Tensor, faces: torch.Tensor, width: int, height: int, radius: float):
    """Numba: ``(B, V, 2)`` pixels → face corners ``(B, F, 3, 2)`` and pixel boxes ``(B, F, 4)``."""
    batch, n_faces = pixels.shape[0], faces.shape[0]
    pixels_np = pixels.detach().contiguous().numpy()
    triangles = np.empty((batch, n_faces, 3, 2), dtype=pixels_np.dtype)
    boxes = np.empty((batch, n_faces, 4), dtype=np.int32)
    faces_np = faces.contiguous().numpy()
    _kernel("gather_faces")[0](pixels_np, vertex_ok.contiguous().numpy(), faces_np, width, height, float(radius), triangles, boxes)
    return triangles, boxes, faces_np


class _SoftLogKeepNumba(torch.autograd.Function):
    """``Σ_f log(1 − sigmoid(−d_f/σ))`` per pixel from projected vertices, with the fused CPU kernels.

    Taking vertices (not per-face corners) lets the kernels gather corners and scatter
    their gradients themselves, which is cheaper than torch's index_select/index_add.
    """

    @staticmethod
    def forward(ctx, pixels, vertex_ok, faces, width, height, sigma, radius):  # type: ignore[override]
        triangles, boxes, faces_np = _gather_faces(pixels, vertex_ok, faces, width, height, radius)
        out = torch.zeros((pixels.shape[0], height, width), dtype=pixels.dtype)
        exact = pixels.dtype == torch.float64  # tables (~2e-6) suffice for float32 work
        kernel, n_threads = _kernel("soft_log_keep")
        kernel(triangles, boxes, height, width, float(sigma), float(radius), exact, _SOFTPLUS_TABLE, n_threads, out.numpy())
        ctx.triangles, ctx.boxes, ctx.faces = triangles, boxes, faces_np
        ctx.sigma, ctx.radius, ctx.n_vertices = sigma, radius, pixels.shape[1]
        return out

    @staticmethod
    def backward(ctx, grad_out):  # type: ignore[override]
        triangles = ctx.triangles
        grad_triangles = np.zeros_like(triangles)
        kernel, n_threads = _kernel("soft_log_keep_backward")
        kernel(triangles, ctx.boxes, float(ctx.sigma), float(ctx.radius), triangles.dtype == np.float64,
               _SIGMOID_TABLE, n_threads, grad_out.contiguous().numpy(), grad_triangles)
        grad_pixels = torch.zeros((triangles.shape[0], ctx.n_vertices, 2), dtype=grad_out.dtype)
        _kernel("scatter_to_vertices")[0](grad_triangles, ctx.faces, grad_pixels.numpy())
        return grad_pixels, None, None, None, None, None, None


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
    vertices_view = transform_points(vertices, mesh_to_view)
    radius = settings.blur_radius_px
    if _use_numba(settings, vertices_view):
        pixels, vertex_ok = project_points(vertices_view, camera, settings.near_mm)
        log_keep = _SoftLogKeepNumba.apply(pixels, vertex_ok, faces, camera.width, camera.height, settings.sigma_px, radius)
    else:
        triangles, valid = project_triangles(vertices_view, faces, camera, settings.near_mm)
        fragments = rasterize_fragments(triangles, valid, camera.width, camera.height, radius)
        log_keep = soft_log_keep_from_fragments(fragments, settings.sigma_px, radius)
    return alpha_from_log_keep(log_keep)


def render_hard_silhouette(
    vertices: torch.Tensor,
    faces: torch.Tensor,
    mesh_to_view: torch.Tensor,
    camera: Camera,
    settings: SilhouetteSettings = SilhouetteSettings(),
) -> torch.Tensor:
    """Binary silhouettes ``(B, H, W)`` bool: pixel centres inside (or on) some face.

    Equals the soft silhouette thresholded at 0.5 as σ → 0.
    """
    with torch.no_grad():
        vertices_view = transform_points(vertices, mesh_to_view)
        if _use_numba(settings, vertices_view):
            pixels, vertex_ok = project_points(vertices_view, camera, settings.near_mm)
            triangles, boxes, _ = _gather_faces(pixels, vertex_ok, faces, camera.width, camera.height, 0.0)
            out = torch.zeros((pixels.shape[0], camera.height, camera.width), dtype=torch.bool)
            kernel, n_threads = _kernel("coverage")
            kernel(triangles, boxes, camera.height, camera.width, n_threads, out.numpy())
            return out
        triangles, valid = project_triangles(vertices_view, faces, camera, settings.near_mm)
        return hard_from_fragments(rasterize_fragments(triangles, valid, camera.width, camera.height, 1e-9))


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
