"""A small U-Net that maps a normalised X-ray angiogram ``(B, 1, H, W)`` to vessel logits ``(B, 1, H, W)``.

Four levels (three 2× poolings), two 3×3 convolutions with batch norm and ReLU per level, skip connections by
concatenation, bilinear upsampling. ``H`` and ``W`` must be multiples of 8 (:func:`padded_to_level`). With the
default 8 → 64 channels it has ~120 k parameters (0.5 MB of float32) and costs ~12 k multiply-adds per pixel: a
512² image runs in ~0.1–0.2 s on 2 CPU cores.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn
from torch.nn import functional as F


@dataclass(frozen=True)
class UNetSettings:
    """Attributes:
        base_channels: channels of the first level; each level below doubles them.
        levels: resolution levels (``levels - 1`` poolings).
    """

    base_channels: int = 8
    levels: int = 4

    @property
    def multiple_px(self) -> int:
        return 2 ** (self.levels - 1)


def _block(channels_in: int, channels_out: int) -> nn.Sequential:
    return nn.Sequential(
        nn.Conv2d(channels_in, channels_out, 3, padding=1, bias=False), nn.BatchNorm2d(channels_out), nn.ReLU(inplace=True),
        nn.Conv2d(channels_out, channels_out, 3, padding=1, bias=False), nn.BatchNorm2d(channels_out), nn.ReLU(inplace=True),
    )


class VesselUNet(nn.Module):
    """``forward(image (B, 1, H, W)) -> logits (B, 1, H, W)``; ``H, W`` multiples of ``settings.multiple_px``."""

    def __init__(self, settings: UNetSettings = UNetSettings()) -> None:
        super().__init__()
        self.settings = settings
        widths = [settings.base_channels * 2 ** level for level in range(settings.levels)]
        self.down = nn.ModuleList([_block(1, widths[0])] + [_block(widths[i - 1], widths[i])
                                                            for i in range(1, len(widths))])
        self.up = nn.ModuleList([_block(widths[i] + widths[i + 1], widths[i]) for i in range(len(widths) - 1)])
        self.head = nn.Conv2d(widths[0], 1, 1)

    def forward(self, image: torch.Tensor) -> torch.Tensor:
        skips = []
        features = image
        for level, block in enumerate(self.down):
            if level:
                features = F.max_pool2d(features, 2)
            features = block(features)
            skips.append(features)
        for level in reversed(range(len(self.up))):
            features = F.interpolate(features, scale_factor=2.0, mode="bilinear", align_corners=False)
            features = self.up[level](torch.cat([skips[level], features], dim=1))
        return self.head(features)


def padded_to_level(image: torch.Tensor, multiple_px: int) -> tuple[torch.Tensor, tuple[int, int]]:
    """``image (B, C, H, W)`` reflect-padded at the bottom and right to multiples of ``multiple_px``;
    returns it and the original ``(H, W)``."""
    height, width = image.shape[-2:]
    pad_h, pad_w = (-height) % multiple_px, (-width) % multiple_px
    if pad_h or pad_w:
        image = F.pad(image, (0, pad_w, 0, pad_h), mode="replicate")
    return image, (height, width)
