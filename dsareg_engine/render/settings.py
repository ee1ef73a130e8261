"""Settings of the silhouette renderer, as a small immutable dataclass."""

from __future__ import annotations

import math
from dataclasses import dataclass

BACKENDS = ("auto", "numba", "torch")


@dataclass(frozen=True)
class SilhouetteSettings:
    """How soft silhouettes are drawn.

    Attributes:
        sigma_px: Width of the sigmoid edge, in pixels of the rendered image. A face's
            coverage of a pixel at signed distance ``d`` (px, negative inside) is
            ``sigmoid(-d / sigma_px)``. Large = wide capture, small = sharp.
        cutoff: A face stops touching pixels where its coverage falls below this
            probability; it sets the blur radius ``sigma_px · ln(1/cutoff − 1)``.
        near_mm: Faces with any vertex closer to the source than this (view z, mm) are
            **dropped** (not clipped): they sit on or behind the source and have no
            meaningful projection.
        backend: ``"numba"`` (fused CPU kernels with analytic backward), ``"torch"``
            (pure PyTorch; used on CUDA), or ``"auto"`` (numba for CPU tensors when
            importable, otherwise torch).
    """

    sigma_px: float = 1.0
    cutoff: float = 1e-3
    near_mm: float = 1.0
    backend: str = "auto"

    def __post_init__(self) -> None:
        if not self.sigma_px > 0:
            raise ValueError(f"sigma_px must be > 0, got {self.sigma_px}")
        if not 0 < self.cutoff < 0.5:
            raise ValueError(f"cutoff must be in (0, 0.5), got {self.cutoff}")
        if self.backend not in BACKENDS:
            raise ValueError(f"backend must be one of {BACKENDS}, got {self.backend!r}")

    @property
    def blur_radius_px(self) -> float:
        """Distance (px) beyond which a face no longer touches a pixel."""
        return self.sigma_px * math.log(1.0 / self.cutoff - 1.0)
