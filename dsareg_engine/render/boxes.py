"""Per-face pixel bounding boxes: the only pixels a face may touch."""

from __future__ import annotations

import torch


def face_pixel_boxes(
    triangles: torch.Tensor, valid: torch.Tensor, width: int, height: int, radius_px: float
) -> torch.Tensor:
    """Inclusive pixel ranges whose centres lie within ``radius_px`` of each face's box.

    (The torch path's boxes; ``kernels_numba.gather_faces`` computes the same boxes in its
    own pass, and the backend-agreement tests hold the two equal.)

    Pixel centres are at integer ``(u, v)``, so a face spanning ``[u_min, u_max]`` touches
    columns ``ceil(u_min − r) … floor(u_max + r)``, clamped to the image. Invalid faces and
    faces entirely off the image get an empty box (``x0 > x1``).

    Args:
        triangles: ``(B, F, 3, 2)`` pixel coordinates.
        valid: ``(B, F)`` bool.

    Returns:
        ``(B, F, 4)`` int32 boxes ``[x0, x1, y0, y1]``.
    """
    with torch.no_grad():
        low = triangles.amin(dim=2) - radius_px  # (B, F, 2)
        high = triangles.amax(dim=2) + radius_px
        # Clamp in float first so huge coordinates cannot overflow the integer cast.
        limit = torch.tensor([width - 1, height - 1], dtype=triangles.dtype, device=triangles.device)
        first = torch.ceil(low).clamp(min=torch.zeros_like(limit) - 1, max=limit + 1)
        last = torch.floor(high).clamp(min=torch.zeros_like(limit) - 1, max=limit + 1)
        first = torch.maximum(first, torch.zeros_like(first))
        last = torch.minimum(last, limit.expand_as(last))
        boxes = torch.stack([first[..., 0], last[..., 0], first[..., 1], last[..., 1]], dim=-1).to(torch.int32)
        empty = ~valid | (boxes[..., 0] > boxes[..., 1]) | (boxes[..., 2] > boxes[..., 3])
        boxes[empty] = torch.tensor([1, 0, 1, 0], dtype=torch.int32, device=boxes.device)
    return boxes
