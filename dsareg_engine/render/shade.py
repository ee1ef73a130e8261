"""Shaders: fragments (signed distances) → silhouettes.

The soft silhouette aggregates faces like PyTorch3D's SoftSilhouetteShader::

    alpha(p) = 1 − Π_f (1 − sigmoid(−d_f(p) / σ))

computed in log space, ``log Π = Σ −softplus(−d/σ)``, so deep-inside pixels neither
underflow nor lose their gradient. Faces stop at the blur radius ``r``; each term is
shifted by its value at ``r`` so it fades to exactly 0 there and the image stays a
continuous function of the pose (a hard cut makes line searches stumble).
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F

from .rasterize_torch import Fragments


def soft_log_keep_from_fragments(fragments: Fragments, sigma_px: float, radius_px: float) -> torch.Tensor:
    """``Σ_f [log(1 − sigmoid(−d_f/σ)) − log(1 − sigmoid(−r/σ))]`` per pixel: ``(B, H, W)``, ≤ 0."""
    batch, height, width = fragments.shape
    floor = -math.log1p(math.exp(-radius_px / sigma_px))
    contributions = -F.softplus(-fragments.signed_distance / sigma_px) - floor
    total = torch.zeros(batch * height * width, dtype=contributions.dtype, device=contributions.device)
    return total.index_add(0, fragments.pixel_index, contributions).view(batch, height, width)


def alpha_from_log_keep(log_keep: torch.Tensor) -> torch.Tensor:
    """``1 − exp(log_keep)``, accurate near both 0 and 1."""
    return -torch.expm1(log_keep)


def hard_from_fragments(fragments: Fragments) -> torch.Tensor:
    """Binary coverage ``(B, H, W)``: some face has ``d ≤ 0`` at the pixel centre."""
    batch, height, width = fragments.shape
    mask = torch.zeros(batch * height * width, dtype=torch.bool, device=fragments.pixel_index.device)
    mask[fragments.pixel_index[fragments.signed_distance <= 0]] = True
    return mask.view(batch, height, width)
