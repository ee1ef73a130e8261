"""Soft silhouettes with their per-pixel Jacobian w.r.t. a few parameters of the pose (CPU, numba).

``alpha = 1 − exp(log_keep)`` (see :mod:`.silhouette`), so ``∂alpha/∂θ = (alpha − 1) · ∂log_keep/∂θ``;
``∂log_keep/∂θ`` comes from :func:`.jacobian_numba.soft_log_keep_tangents` given how each projected
vertex moves, which follows from ``∂mesh_to_view/∂θ`` by the pinhole's quotient rule.
"""

from __future__ import annotations

import numpy as np
import torch

from .camera import Camera, project_points, transform_points
from .settings import SilhouetteSettings

MIN_LOG_KEEP = -12.0
"""Pixels with ``log_keep`` below this (``1 − alpha < 7e-6``) get no Jacobian: it is ``exp(log_keep)`` times a
bounded slope, negligible there; skipping them skips the faces inside the silhouette."""


_KERNEL_PAIRS: dict = {}


def jacobian_kernel(name: str) -> tuple:
    """(the :mod:`.jacobian_numba` kernel ``name`` for this thread's budget: its serial twin on 1 thread
    (see :mod:`.serial_kernels`), the thread count)."""
    from . import jacobian_numba
    from .serial_kernels import KernelPair
    from .silhouette import _threads

    if name not in _KERNEL_PAIRS:
        from ..kernels.compile_lock import wait_for_group

        wait_for_group("tracking")  # a background helper may be compiling them right now
        _KERNEL_PAIRS[name] = KernelPair(getattr(jacobian_numba, name))
    n_threads = _threads()
    return _KERNEL_PAIRS[name].pick(n_threads), n_threads


def jacobian_available(device: torch.device) -> bool:
    """The Jacobian kernel runs where the numba renderer does: CPU tensors with numba importable."""
    from .silhouette import numba_available

    return device.type == "cpu" and numba_available()


def pixel_tangents(vertices: torch.Tensor, mesh_to_view: torch.Tensor, mesh_to_view_tangents: torch.Tensor,
                   camera: Camera) -> torch.Tensor:
    """∂(u, v)/∂θ_k of every projected vertex: ``(B, V, 2, K)``.

    Args:
        vertices: ``(V, 3)`` mesh-frame mm.
        mesh_to_view: ``(B, 4, 4)``.
        mesh_to_view_tangents: ``(B, K, 4, 4)`` = ∂mesh_to_view/∂θ_k.
    """
    points = transform_points(vertices, mesh_to_view)  # (B, V, 3)
    moved = (torch.einsum("bkij,vj->bkvi", mesh_to_view_tangents[..., :3, :3], vertices)
             + mesh_to_view_tangents[..., None, :3, 3])  # (B, K, V, 3)
    z = points[..., 2].clamp_min(1e-9)[:, None]  # (B, 1, V)
    fx, fy = camera.focal_px
    du = fx * (moved[..., 0] * z - points[:, None, :, 0] * moved[..., 2]) / z**2
    dv = fy * (moved[..., 1] * z - points[:, None, :, 1] * moved[..., 2]) / z**2
    return torch.stack([du, dv], dim=-1).permute(0, 2, 3, 1).contiguous()  # (B, V, 2, K)


def soft_log_keep_tangents(
    vertices: torch.Tensor, faces: torch.Tensor, mesh_to_view: torch.Tensor, mesh_to_view_tangents: torch.Tensor,
    camera: Camera, settings: SilhouetteSettings = SilhouetteSettings(), min_log_keep: float = MIN_LOG_KEEP,
) -> tuple[np.ndarray, np.ndarray]:
    """``log_keep`` ``(B, H, W)`` (``alpha = 1 − exp(log_keep)``) and ``∂log_keep/∂θ`` ``(B, H, W, K)``, numpy.

    Args:
        vertices: ``(V, 3)`` mesh-frame mm; faces ``(F, 3)`` int64.
        mesh_to_view: ``(B, 4, 4)``; mesh_to_view_tangents: ``(B, K, 4, 4)`` its derivatives.
        camera, settings: as for :func:`.silhouette.render_soft_silhouette` (same values).
        min_log_keep: pixels covered more deeply get zero tangents (see MIN_LOG_KEEP; −inf: none skipped).

    Raises:
        RuntimeError: off the CPU or without numba (see :func:`jacobian_available`).
    """
    from . import jacobian_numba
    from .silhouette import _SIGMOID_TABLE, _SOFTPLUS_TABLE, _kernel

    if not jacobian_available(vertices.device) or mesh_to_view_tangents.shape[1] != jacobian_numba.PARAMETERS:
        raise RuntimeError("the silhouette Jacobian needs the numba renderer (CPU tensors) and 6 parameters")
    with torch.no_grad():
        pixels, vertex_ok = project_points(transform_points(vertices, mesh_to_view), camera, settings.near_mm)
        tangents = pixel_tangents(vertices, mesh_to_view, mesh_to_view_tangents, camera).to(pixels.dtype)
    radius = settings.blur_radius_px
    batch, n_params, n_faces = pixels.shape[0], tangents.shape[-1], faces.shape[0]
    faces_np = faces.contiguous().numpy()
    pixels_np = pixels.contiguous().numpy()
    triangles = np.empty((batch, n_faces, 3, 2), dtype=pixels_np.dtype)
    boxes = np.empty((batch, n_faces, 4), dtype=np.int32)
    corner_tangents = np.empty((batch, n_faces, 6, n_params), dtype=pixels_np.dtype)
    jacobian_numba.gather_faces_with_tangents(pixels_np, vertex_ok.contiguous().numpy(), tangents.numpy(), faces_np,
                                              camera.width, camera.height, float(radius), triangles, boxes, corner_tangents)
    exact = triangles.dtype == np.float64
    log_keep = np.zeros((batch, camera.height, camera.width), dtype=triangles.dtype)
    soft_log_keep, n_threads = _kernel("soft_log_keep")
    soft_log_keep(triangles, boxes, camera.height, camera.width, float(settings.sigma_px), float(radius), exact,
                  _SOFTPLUS_TABLE, n_threads, log_keep)
    log_keep_tangents = np.zeros((batch, camera.height, camera.width, n_params), dtype=triangles.dtype)
    tangents_kernel, n_threads = jacobian_kernel("soft_log_keep_tangents")
    tangents_kernel(triangles, corner_tangents, boxes, float(settings.sigma_px), float(radius), exact,
                    _SIGMOID_TABLE, log_keep, float(min_log_keep), n_threads, log_keep_tangents)
    return log_keep, log_keep_tangents


def render_soft_silhouette_jacobian(
    vertices: torch.Tensor, faces: torch.Tensor, mesh_to_view: torch.Tensor, mesh_to_view_tangents: torch.Tensor,
    camera: Camera, settings: SilhouetteSettings = SilhouetteSettings(), min_log_keep: float = MIN_LOG_KEEP,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Soft silhouettes ``(B, H, W)`` and their Jacobians ``(B, H, W, K)`` (no autograd graph); arguments as
    :func:`soft_log_keep_tangents`."""
    log_keep, log_keep_tangents = soft_log_keep_tangents(vertices, faces, mesh_to_view, mesh_to_view_tangents, camera,
                                                         settings, min_log_keep)
    keep = torch.from_numpy(np.exp(log_keep))
    return torch.from_numpy(-np.expm1(log_keep)), torch.from_numpy(log_keep_tangents) * -keep[..., None]
