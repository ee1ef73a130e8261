"""Native or subtracted: how a multi-frame XA run is stored, decided once, with its margin.

**Tags first.** A Mask Subtraction Sequence or Recommended Viewing Mode (0028,1090) ``SUB``: native
(the viewer subtracts); a Mask Subtraction Sequence whose every item says ``MaskOperation NONE`` (legal:
"no subtraction", as cardiac cines carry it): *unsubtracted*, the frames read as stored. Image Type or
Derivation Description naming a subtraction: subtracted.

**Otherwise the content.** A native run shows the same anatomy (bone, soft tissue, a catheter) in
every frame; a subtracted run's frames before contrast are noise. The measure is the structure of an
early frame over the frame-to-frame noise, both **at a physical scale** so that it does not change
with the pixel size or the dose per pixel: each early frame is first area-averaged onto a grid of
``grid_mm`` detector pixels (the spacing from Imager Pixel Spacing, else the field of view assumed
``assumed_fov_mm``), then band-passed between ``grid_mm`` and ``coarse_mm`` (Gaussian σ). The
structure is the band-passed frame's standard deviation; the noise the robust spread of the
band-passed difference of two adjacent frames over √2 (the quietest pair of the first four frames,
so that contrast arriving early does not count as noise). Native when the ratio exceeds
``threshold``; a ratio within ``band`` of it is a close call (:mod:`.input_decisions`).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from .input_decisions import InputDecision

BASIS = "structure common to the early frames / frame-to-frame noise, at 1-8 mm"


@dataclass(frozen=True)
class RunKindSettings:
    """Attributes:
        grid_mm: detector pixel size the frames are averaged onto before measuring.
        coarse_mm: the band's coarse end (Gaussian σ, mm); the fine end is one grid pixel.
        assumed_fov_mm: field of view assumed when the file gives no pixel spacing.
        threshold: structure/noise ratio above which a run is native.
        band: half-width of the close-call band around ``threshold``.
    """

    grid_mm: float = 1.0
    coarse_mm: float = 8.0
    assumed_fov_mm: float = 250.0
    threshold: float = 4.0
    band: float = 2.0


def _spacing_mm(dataset, shape: tuple[int, int], settings: RunKindSettings) -> float:
    from .dicom_xa import find_tag

    for keyword in ("ImagerPixelSpacing", "PixelSpacing"):
        value = find_tag(dataset, keyword)
        try:
            spacing = float(min(float(v) for v in value))
        except (TypeError, ValueError):
            continue
        if np.isfinite(spacing) and spacing > 0:
            return spacing
    return settings.assumed_fov_mm / max(shape)


def grid_factor(dataset, shape: tuple[int, int], settings: RunKindSettings = RunKindSettings()) -> tuple[int, float]:
    """``(pixels per side averaged into one grid pixel, the grid pixel's size mm)``: about ``grid_mm``."""
    spacing = _spacing_mm(dataset, shape, settings)
    factor = max(1, int(round(settings.grid_mm / spacing)))
    return factor, factor * spacing


def on_grid(frame: np.ndarray, factor: int) -> np.ndarray:
    """``frame`` ``(H, W)`` area-averaged ``factor`` × ``factor`` (the remainder rows/columns dropped)."""
    frame = frame.astype(np.float32)
    if factor <= 1:
        return frame
    height, width = frame.shape[0] // factor, frame.shape[1] // factor
    return cv2.resize(frame[:height * factor, :width * factor], (width, height), interpolation=cv2.INTER_AREA)


def _robust_std(values: np.ndarray) -> float:
    values = values.ravel()
    return float(1.4826 * np.median(np.abs(values - np.median(values))))


def static_ratio(stack: np.ndarray, spacing_mm: float, settings: RunKindSettings = RunKindSettings()) -> float:
    """Structure of an early frame over the frame-to-frame noise at ``grid_mm`` .. ``coarse_mm``.

    Args:
        stack: ``(N, H, W)`` stored values (any monotone encoding; N ≥ 2).
        spacing_mm: the detector pixel spacing.
    """
    factor = max(1, int(round(settings.grid_mm / spacing_mm)))
    coarse_px = settings.coarse_mm / (spacing_mm * factor)
    early = [on_grid(frame, factor) for frame in stack[:4]]

    def band(image: np.ndarray) -> np.ndarray:
        return cv2.GaussianBlur(image, (0, 0), 1.0) - cv2.GaussianBlur(image, (0, 0), coarse_px)

    noise, first = min((_robust_std(band(early[i + 1] - early[i])) / np.sqrt(2.0), i) for i in range(len(early) - 1))
    structure = float(np.std(band(early[first])))
    if structure <= 0:
        return 0.0
    return structure / max(noise, 1e-6 * float(np.abs(early[first]).mean()) + 1e-12)


def _operations(dataset) -> list[str]:
    try:
        return [str(getattr(item, "MaskOperation", "") or "").strip().upper() for item in dataset.MaskSubtractionSequence]
    except Exception:  # noqa: BLE001 - a malformed sequence is told by the recipe's own checks (xa_recipe)
        return []


def _tagged(dataset) -> tuple[str, str] | None:
    if "MaskSubtractionSequence" in dataset:
        operations = _operations(dataset)
        if operations and all(operation == "NONE" for operation in operations):
            return "unsubtracted", "its Mask Subtraction Sequence says NONE (no subtraction): frames read as stored"
        return "native", "it carries a Mask Subtraction Sequence"
    mode = str(getattr(dataset, "RecommendedViewingMode", "") or "").strip().upper()
    if mode == "SUB":
        return "native", "Recommended Viewing Mode is SUB"
    image_type = "\\".join(str(v) for v in (getattr(dataset, "ImageType", None) or [])).upper()
    derivation = str(getattr(dataset, "DerivationDescription", "") or "").upper()
    if "SUBTRACT" in image_type or "SUBTRACT" in derivation:
        return "subtracted", "its Image Type / Derivation Description says subtracted"
    return None


def decide_run_kind(dataset, stack: np.ndarray, field_name: str,
                    settings: RunKindSettings = RunKindSettings()) -> tuple[str, str, InputDecision]:
    """``("native" | "subtracted" | "unsubtracted", why, decision)`` for a multi-frame run (``stack`` ``(N, H, W)``,
    N ≥ 2)."""
    tagged = _tagged(dataset)
    if tagged is not None:
        kind, why = tagged
        return kind, why, InputDecision(field_name, "run kind", kind, why, source="tag")
    spacing = _spacing_mm(dataset, stack.shape[1:], settings)
    ratio = static_ratio(stack, spacing, settings)
    decision = InputDecision(field_name, "run kind", "native" if ratio > settings.threshold else "subtracted",
                             BASIS, round(float(ratio), 3), settings.threshold, settings.band)
    if ratio > settings.threshold:
        return "native", f"anatomy in every frame (structure {ratio:.1f}x the frame-to-frame noise at 1-8 mm)", decision
    return "subtracted", f"no anatomy common to the frames (structure {ratio:.1f}x the noise at 1-8 mm)", decision
