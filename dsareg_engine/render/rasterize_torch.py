"""Pure-PyTorch rasterizer: geometry → (face, pixel, signed distance) fragments.

Every face is paired with the pixels of its own box (grown by the blur radius), so
the cost follows the pixels the mesh covers, whatever the face sizes. The ragged
face→pixel enumeration is built with ``repeat_interleave``; everything after it is
plain autograd, which makes this the reference implementation and the CUDA path.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from .boxes import face_pixel_boxes


@dataclass
class Fragments:
    """Face–pixel pairs within the blur radius.

    Attributes:
        pixel_index: ``(P,)`` int64 flat index ``b·H·W + v·W + u`` into the ``(B, H, W)`` image.
        face_index: ``(P,)`` int64 flat index ``b·F + f``.
        signed_distance: ``(P,)`` px from the pixel centre to the face, negative inside.
        shape: ``(B, H, W)`` of the image.
    """

    pixel_index: torch.Tensor
    face_index: torch.Tensor
    signed_distance: torch.Tensor
    shape: tuple[int, int, int]


def signed_distance_to_triangles(points: torch.Tensor, triangles: torch.Tensor) -> torch.Tensor:
    """Signed distance (px, negative inside) from points to triangles, pairwise.

    Args:
        points: ``(P, 2)`` pixel centres.
        triangles: ``(P, 3, 2)`` corners.

    Returns:
        ``(P,)``.
    """
    starts = triangles
    edges = torch.roll(triangles, shifts=-1, dims=1) - triangles  # ab, bc, ca: (P, 3, 2)
    rel = points[:, None, :] - starts  # (P, 3, 2)
    length2 = (edges * edges).sum(-1)
    t = ((rel * edges).sum(-1) / length2.clamp_min(1e-30)).clamp(0.0, 1.0)
    offset = rel - t[..., None] * edges
    dist2 = (offset * offset).sum(-1).amin(dim=1)
    # Clamp before sqrt so the gradient stays finite at distance zero.
    dist = dist2.clamp_min(1e-24).sqrt()
    cross = edges[..., 0] * rel[..., 1] - edges[..., 1] * rel[..., 0]  # (P, 3) edge functions
    area2 = edges[:, 0, 0] * (-edges[:, 2, 1]) - edges[:, 0, 1] * (-edges[:, 2, 0])
    inside_pos = (cross >= 0).all(-1) & (area2 > 0)
    inside_neg = (cross <= 0).all(-1) & (area2 < 0)
    return torch.where(inside_pos | inside_neg, -dist, dist)


def rasterize_fragments(triangles: torch.Tensor, valid: torch.Tensor, width: int, height: int, radius_px: float) -> Fragments:
    """All (face, pixel) pairs whose signed distance is below ``radius_px``.

    Args:
        triangles: ``(B, F, 3, 2)`` pixel coordinates.
        valid: ``(B, F)`` bool; invalid faces produce no fragments.
    """
    batch, n_faces = triangles.shape[:2]
    device = triangles.device
    boxes = face_pixel_boxes(triangles, valid, width, height, radius_px).reshape(-1, 4).long()
    box_w = (boxes[:, 1] - boxes[:, 0] + 1).clamp_min(0)
    box_h = (boxes[:, 3] - boxes[:, 2] + 1).clamp_min(0)
    counts = box_w * box_h
    face_index = torch.repeat_interleave(torch.arange(batch * n_faces, device=device), counts)
    starts = torch.cumsum(counts, 0) - counts
    local = torch.arange(face_index.numel(), device=device) - starts[face_index]
    u = boxes[face_index, 0] + local % box_w[face_index]
    v = boxes[face_index, 2] + local // box_w[face_index]
    points = torch.stack([u, v], dim=-1).to(triangles.dtype)
    distance = signed_distance_to_triangles(points, triangles.reshape(-1, 3, 2)[face_index])
    keep = distance < radius_px
    b = face_index // n_faces
    pixel_index = (b * height + v) * width + u
    return Fragments(pixel_index[keep], face_index[keep], distance[keep], (batch, height, width))
