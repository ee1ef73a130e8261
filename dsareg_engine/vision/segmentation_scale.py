"""The pixel pitch a grey-level DSA is segmented at: fine detector pixels area-averaged to a physical scale.

The segmentation (:mod:`.dsa_border`, :mod:`.dsa_coverage`) works in pixels: its smoothing (1 px), its
background scale (16 px), its reach (2–3 px) and its noise floor. Those are physical scales only at a
given pixel pitch, and the noise is too: on the same detector and dose, a pixel half as wide holds a
quarter of the photons, so its noise doubles while a vessel's contrast stays the same. Read at 2048 px
(0.086 mm) a run holds ~220 photons per pixel and the vessels sink into the noise; the same run read at
1024 px (0.17 mm) segments cleanly.

So an image whose detector pixels are finer than about ``pitch_mm`` is area-averaged by the integer
factor that brings its pitch closest to ``pitch_mm`` (the noise averaged as a coarser detector would,
the vessels kept), segmented there, and its coverage brought back onto the image's own pixels by bilinear
interpolation (pixel centres aligned; each coarse pixel's coverage kept, the border within 0.2 px and on
average where the coarse segmentation put it). ``pitch_mm`` = 0.24 mm is the middle (geometric mean) of the
pitches the segmentation was validated at, 512 and 1024 px on a 17.6 cm field (0.34 and 0.17 mm); measured on
generator A at 2048 px (0.086 mm, ~220 photons per pixel), the recall of the tree is 7 % pixel by pixel,
69–76 % averaged 2×2 (0.17 mm: the late-filling distal branches still lost) and 86–92 % averaged 3×3.
Pixels coarser than ``pitch_mm`` / 1.5 (0.16 mm) are segmented as they are: at 512 and 1024 px on that
field nothing changes; a 0.154 mm flat panel read unbinned is averaged 2×2. The factor is read from the pixel
spacing (the image's tags or the geometry file), recorded as an
:class:`~dsareg_engine.io.input_decisions.InputDecision` when it is above 1.

The averaged pitch finds the tree; its borders are only as fine as its pixels. Where the image's own pixels find
that tree too (at least :data:`NATIVE_FOUND_SHARE` of the averaged mask within one averaged pixel of the
pixel-by-pixel ``dsa`` mask: photons enough per pixel), the image is segmented pixel by pixel after all
(:func:`refined_on_pixels`), its sub-pixel borders kept (factor 1: no pitch decision recorded). Synthetic grey
DSA with a catheter and an uneven background at 0.156 mm (phantom, 1024 px): ADD 0.0035–0.0047 mm pixel by
pixel (8a9ae79), 0.008–0.012 mm averaged 2×2 (3112b29); the low-dose images the averaging is for keep it
(0.08 mm, noise σ 0.06–0.12: 61–95 % found).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from ..errors import DsaregInputError
from .segmentation import resolved_method, vessel_coverage_and_choice
from .segmentation_choice import AutoChoice

NATIVE_FOUND_SHARE = 0.97
"""The share of the averaged pitch's mask that the pixel-by-pixel ``dsa`` mask must find (within one averaged pixel)
for the image to be segmented pixel by pixel. Measured: 0.986–0.989 on synthetic grey DSA at 0.156 mm (phantom,
catheter, uneven background), 0.935–0.96 on the paper's mesh there (kept averaged: ADD 0.006–0.007 mm either
way); on the low-dose 0.08 mm test images 0.61 / 0.95 / 0.975 / 0.98 at noise σ 0.12 / 0.06 / 0.03 / 0.015
(recall of the tree pixel by pixel 0.38 / 0.81 / 0.83 / 0.84, averaged 0.87–0.91)."""


@dataclass(frozen=True)
class SegmentationScale:
    """Attributes:
        pitch_mm: the detector pixel pitch segmentation works at; finer pixels are averaged towards it
            (the integer factor nearest ``pitch_mm / spacing``).
    """

    pitch_mm: float = 0.24


def averaging_factor(spacing_mm: float | None, settings: SegmentationScale = SegmentationScale()) -> int:
    """Pixels per side averaged into one segmentation pixel (1: none; unknown spacing: none)."""
    if spacing_mm is None or not np.isfinite(spacing_mm) or spacing_mm <= 0:
        return 1
    return max(1, int(round(settings.pitch_mm / spacing_mm)))


def area_averaged(pixels: np.ndarray, factor: int) -> np.ndarray:
    """``pixels`` ``(H, W)`` averaged ``factor`` × ``factor`` into ``(⌈H/f⌉, ⌈W/f⌉)`` (edges replicated to fill)."""
    height, width = pixels.shape
    padded = cv2.copyMakeBorder(pixels.astype(np.float32), 0, (-height) % factor, 0, (-width) % factor,
                                cv2.BORDER_REPLICATE)
    return cv2.resize(padded, (padded.shape[1] // factor, padded.shape[0] // factor), interpolation=cv2.INTER_AREA)


def back_on_pixels(coverage: np.ndarray, factor: int, shape: tuple[int, int]) -> np.ndarray:
    """A coverage ``(h, w)`` of :func:`area_averaged` pixels on the original ``(H, W)`` pixels: bilinear
    (cv2's half-pixel centres: coarse pixel ``i`` is centred on fine ``f i + (f − 1) / 2``)."""
    fine = cv2.resize(coverage.astype(np.float32), (coverage.shape[1] * factor, coverage.shape[0] * factor),
                      interpolation=cv2.INTER_LINEAR)
    return np.clip(fine[:shape[0], :shape[1]], 0.0, 1.0)


def coverage_at_scale(pixels: np.ndarray, method: str, spacing_mm: float | None, *, field_name: str = "image",
                      settings: SegmentationScale = SegmentationScale(), field_of_view: np.ndarray | None = None
                      ) -> tuple[np.ndarray, int, AutoChoice | None]:
    """``(the registration target (H, W) as :func:`~.segmentation.vessel_coverage` gives it, factor, auto's
    choice or None)``, segmented at the physical pitch (module docstring) when the method resolves to ``"dsa"``
    (factor 1 again where the image's own pixels find the tree: :func:`refined_on_pixels`);
    other methods, masks and pixels at or above ``pitch_mm`` unchanged (factor 1). ``field_of_view``: the
    file's shutter (True inside), averaged with the pixels."""
    factor = averaging_factor(spacing_mm, settings)
    pixels = np.asarray(pixels)
    if factor <= 1 or pixels.ndim != 2 or pixels.dtype == bool or resolved_method(pixels, method) != "dsa" \
            or min(pixels.shape) < 32 * factor:
        coverage, choice = vessel_coverage_and_choice(pixels, method, field_name=field_name,
                                                      field_of_view=field_of_view)
        return coverage, 1, choice
    small = area_averaged(pixels, factor)
    small_field = None if field_of_view is None else area_averaged(field_of_view.astype(np.float32), factor) >= 0.5
    coverage, choice = vessel_coverage_and_choice(small, method, field_name=field_name, field_of_view=small_field)
    averaged = back_on_pixels(np.asarray(coverage, np.float32), factor, pixels.shape)
    if choice is not None and choice.method != "dsa":
        return averaged, factor, choice
    target = refined_on_pixels(pixels, averaged, factor, field_name=field_name, field_of_view=field_of_view)
    return target, factor if target is averaged else 1, choice


def _near(mask: np.ndarray, px: int) -> np.ndarray:
    return cv2.dilate(mask.astype(np.uint8), np.ones((2 * px + 1, 2 * px + 1), np.uint8)).astype(bool)


def refined_on_pixels(pixels: np.ndarray, averaged: np.ndarray, factor: int, *, field_name: str = "image",
                      field_of_view: np.ndarray | None = None) -> np.ndarray:
    """The pixel-by-pixel ``dsa`` coverage of ``pixels`` where it finds at least :data:`NATIVE_FOUND_SHARE` of the
    mask of ``averaged`` (the coverage segmented on ``factor`` × ``factor`` averaged pixels, back on the image's
    pixels) within ``factor`` px, restricted to where ``averaged`` may be vessel; else ``averaged``, unchanged."""
    try:
        native, _ = vessel_coverage_and_choice(pixels, "dsa", field_name=field_name, field_of_view=field_of_view)
    except DsaregInputError:  # nothing found pixel by pixel
        return averaged
    found, kept = native >= 0.5, averaged >= 0.5
    if int((kept & _near(found, factor)).sum()) < NATIVE_FOUND_SHARE * int(kept.sum()):
        return averaged
    return np.where(_near(averaged > 0, factor), native, 0.0).astype(np.float32)
