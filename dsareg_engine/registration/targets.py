"""Target silhouettes per view and pyramid level: resampled masks, border shift, blur, thin-vessel weights."""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
import torch
import torch.nn.functional as F
from scipy import ndimage

from ..geometry.rig import ViewGeometry
from ..render import Camera
from ..vision.vessel_target import binary_mask, is_coverage


@dataclass
class ViewTarget:
    """One view at one pyramid level.

    Attributes:
        view: geometry resampled to this level.
        camera: its render intrinsics.
        target: ``(H, W)`` float in [0, 1] (area-averaged mask, blurred like the renders).
        blur_px: Gaussian blur applied to target and renders at this level.
        weight: ``(H, W)`` float pixel weights with mean 1, or None.
    """

    view: ViewGeometry
    camera: Camera
    target: torch.Tensor
    weight: torch.Tensor | None
    blur_px: float = 0.0


def level_target(
    mask: np.ndarray, view: ViewGeometry, scale: float, blur_px: float, thin_vessel_weighting: bool, dtype: torch.dtype,
    border_shift_px: float = 0.0, signed: np.ndarray | None = None,
) -> ViewTarget:
    """Resample a full-resolution mask ``(H, W)`` (bool, or float coverage in [0, 1]) to ``scale`` and build the level's target.

    ``border_shift_px`` (full-resolution px) moves the mask's border outward (negative: inward)
    first, see :func:`shifted_mask` (``signed``: the mask's signed border distance, if known).
    """
    level_view = view.scaled(scale) if scale != 1.0 else view
    image = shifted_mask(mask, border_shift_px, signed)
    if level_view.image_size != view.image_size:
        image = cv2.resize(image, level_view.image_size, interpolation=cv2.INTER_AREA)
    weight = None
    if thin_vessel_weighting:
        weight = torch.as_tensor(thin_vessel_weights(image > 0.5), dtype=dtype)
    target = gaussian_blur(torch.as_tensor(image, dtype=dtype)[None], blur_px)[0]
    return ViewTarget(level_view, Camera.from_view(level_view), target, weight, blur_px)


SIGNED_DISTANCE_REACH_PX = 8
"""signed_border_distance is exact up to this far outside the mask (+inf beyond): its users only look
within a few px of the border (shifts ≤ 2 px, bands of 3 px), and computing it in the mask's box
plus this margin instead of the whole image saves most of the time on a small vessel tree."""


def mask_box(masks: tuple[np.ndarray, ...], margin_px: int) -> tuple[slice, slice] | None:
    """Rows and columns of the bounding box of all ``masks`` ``(H, W)`` bool, grown by ``margin_px`` and clipped; None if all empty."""
    union = np.logical_or.reduce(masks)
    rows, cols = np.flatnonzero(union.any(axis=1)), np.flatnonzero(union.any(axis=0))
    if len(rows) == 0:
        return None
    height, width = union.shape
    return (slice(max(0, rows[0] - margin_px), min(height, rows[-1] + margin_px + 1)),
            slice(max(0, cols[0] - margin_px), min(width, cols[-1] + margin_px + 1)))


def signed_border_distance(mask: np.ndarray) -> np.ndarray:
    """Signed distance (px) from each pixel centre to the mask's border, negative inside: ``(H, W)`` float32.

    The border is taken half a pixel beyond the outermost pixel centres, so the pixels just
    inside read −0.5 and those just outside +0.5. A coverage map (float in [0, 1]) is read
    as that 1-px ramp: a partly covered pixel c lies ``0.5 − c`` from the border (sub-pixel);
    the others take the distance of its half-covered binary mask. Exact inside the mask's box
    grown by SIGNED_DISTANCE_REACH_PX (every mask pixel and all background within that reach),
    +inf beyond.
    """
    binary = binary_mask(mask)
    signed = np.full(mask.shape, np.inf, dtype=np.float32)
    box = mask_box((binary,), SIGNED_DISTANCE_REACH_PX)
    if box is None:
        return signed
    # In the box the distances are those of the whole image: every mask pixel is in it, and the
    # background pixel nearest a mask pixel is never outside it (clamping it to the box, whose
    # margin is background, comes no farther).
    pixels = binary[box].astype(np.uint8)
    inside = cv2.distanceTransform(pixels, cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    outside = cv2.distanceTransform(1 - pixels, cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    signed[box] = np.where(binary[box], 0.5 - inside, outside - 0.5)
    if is_coverage(mask):
        partial = (mask > 0.0) & (mask < 1.0)
        signed[partial] = 0.5 - mask[partial]
    return signed


def shifted_mask(mask: np.ndarray, shift_px: float, signed: np.ndarray | None = None) -> np.ndarray:
    """Coverage ``(H, W)`` float32 in [0, 1] of ``mask`` with its border moved outward by ``shift_px``.

    Each pixel's coverage is a 1-px linear ramp across the moved border, evaluated at its
    centre's signed distance (``signed``: :func:`signed_border_distance` of the mask, computed
    when not given). A shift of 0 returns the mask itself (a coverage map unchanged); negative
    shifts move it inward.
    """
    if shift_px == 0.0:
        return mask.astype(np.float32)
    if signed is None:
        signed = signed_border_distance(mask)
    return np.clip(0.5 - signed + shift_px, 0.0, 1.0).astype(np.float32)


def gaussian_kernel(sigma_px: float) -> np.ndarray:
    """Normalized 1-D Gaussian of standard deviation ``sigma_px`` over ±ceil(3σ) (at least ±1) px, float64."""
    half = max(1, int(math.ceil(3.0 * sigma_px)))
    kernel = np.exp(-0.5 * (np.arange(-half, half + 1, dtype=np.float64) / sigma_px) ** 2)
    return kernel / kernel.sum()


def gaussian_blur(images: torch.Tensor, sigma_px: float) -> torch.Tensor:
    """Separable Gaussian blur of ``(B, H, W)`` images (zero padding); identity for σ = 0.

    Applied to the rendered silhouettes and to the targets alike, so the blur widens the
    capture range without moving the optimum.

    On the CPU it is one autograd node (:class:`_CpuBlur`: OpenCV's separable filter, forward and backward);
    elsewhere weighted sums of shifted slices.
    """
    if sigma_px <= 0:
        return images
    if images.device.type == "cpu" and images.dtype in (torch.float32, torch.float64):
        return _CpuBlur.apply(images, sigma_px)
    kernel = torch.as_tensor(gaussian_kernel(sigma_px), dtype=images.dtype, device=images.device)
    half = len(kernel) // 2
    # Weighted sums of shifted slices: for one channel and a short kernel this is several
    # times faster than conv2d, forward and especially backward.
    padded = F.pad(images, (half, half, 0, 0))
    width = images.shape[-1]
    rows = sum(kernel[k] * padded[..., :, k : k + width] for k in range(2 * half + 1))
    padded = F.pad(rows, (0, 0, half, half))
    height = images.shape[-2]
    return sum(kernel[k] * padded[..., k : k + height, :] for k in range(2 * half + 1))


def _separable_blur(images: torch.Tensor, kernel: np.ndarray) -> torch.Tensor:
    """``(B, H, W)`` CPU images blurred by ``kernel`` along both axes, zero padding (OpenCV), same dtype."""
    array = images.detach().contiguous().numpy()
    kernel = kernel.astype(array.dtype)
    out = np.empty_like(array)
    for index in range(array.shape[0]):
        out[index] = cv2.sepFilter2D(array[index], -1, kernel, kernel, borderType=cv2.BORDER_CONSTANT)
    return torch.from_numpy(out)


class _CpuBlur(torch.autograd.Function):
    """The Gaussian blur as a single autograd node on the CPU.

    The shifted-slice sums made 2 × (2·⌈3σ⌉ + 1) slice and product nodes per blur, each of whose backward
    fills a full-size zero tensor: at the 2-px blur of the coarsest level with 8 starts (autoinit, 170 px)
    forward + backward took 18.8 ms, here 2.1 ms (1 thread). The kernel is symmetric and the padding zero,
    so the backward (the adjoint) is the same blur of the incoming gradient.
    """

    @staticmethod
    def forward(ctx, images: torch.Tensor, sigma_px: float) -> torch.Tensor:
        ctx.kernel = gaussian_kernel(sigma_px)
        return _separable_blur(images, ctx.kernel)

    @staticmethod
    def backward(ctx, grad: torch.Tensor):
        return _separable_blur(grad, ctx.kernel), None


def thin_vessel_weights(mask: np.ndarray, max_ratio: float = 8.0) -> np.ndarray:
    """Per-pixel weights ``∝ 1 / local vessel radius`` so thin branches count like thick ones.

    The local radius of a vessel pixel is the largest inside-distance in its
    neighbourhood (≈ the centreline distance to the wall); background pixels take the
    radius of the nearest vessel pixel. Weights are capped at ``max_ratio`` × the
    smallest and normalised to mean 1. Returns ``(H, W)`` float32.
    """
    if not mask.any():
        return np.ones(mask.shape, np.float32)
    inside = ndimage.distance_transform_edt(mask)
    radius = ndimage.grey_dilation(inside, size=(5, 5)) * mask
    _, (rows, cols) = ndimage.distance_transform_edt(~mask, return_indices=True)
    radius = radius[rows, cols]
    radius = np.clip(radius, max(radius.max() / max_ratio, 0.5), None)
    weight = 1.0 / radius
    return (weight / weight.mean()).astype(np.float32)
