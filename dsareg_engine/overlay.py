"""Overlay images a person can read: the DSA image (or the vessel mask) with the initial and
registered silhouette contours, a caption (view, Dice, verdict, job) and a scale bar in mm.

Layout: the region around the vessels and both contours (:func:`crop_box`), enlarged by a
whole factor when it is small so contours and text stay legible, then a caption band under it. Vessels are shown
dark on a light background, as DSA is read; the initial contour is blue, the registered one
orange (a pair that stays distinct for red-green colour blindness).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

INITIAL_BGR = (200, 110, 0)  # blue
FINAL_BGR = (0, 110, 255)  # orange
UNMATCHED_BGR = (200, 40, 200)  # magenta: model parts with no vessel under them
UNMATCHED_ALPHA = 0.55
BACKGROUND_GREY = 236
TARGET_GREY = 120
CAPTION_BG = (40, 40, 40)
GOOD_RGB = (120, 220, 120)
BAD_RGB = (255, 120, 110)
MIN_SIDE_PX = 512
MAX_UPSCALE = 4


@dataclass
class Caption:
    """What the caption band says; every field is optional.

    Attributes:
        view: view name (``"ap"`` / ``"lat"``), shown upper-case.
        dice: Dice of the registered silhouette with the target mask.
        verdict: short verdict text (``"converged"``, ``"NOT converged"``, or the engine's verdict).
        ok: colours the verdict green (True) or red (False).
        job: job id or another label of the case.
        stage: animation frames: the optimization stage and iteration.
        mm_per_px: image pixel size at the vessel's depth (draws the scale bar).
        final_label: legend of the orange contour (animation frames: ``"current"``).
        dice_label: how the Dice is named (animation frames: measured on the smaller preview).
        frame: which frame of a multi-frame run the image is (e.g. ``"frame 7 of 10 - mask 0,1"``).
    """

    view: str | None = None
    dice: float | None = None
    verdict: str | None = None
    ok: bool | None = None
    job: str | None = None
    stage: str | None = None
    mm_per_px: float | None = None
    final_label: str = "registered"
    dice_label: str = "Dice"
    frame: str | None = None
    unmatched_label: str | None = None
    """Legend of the magenta fill (model parts outside the vessels), when the overlay shows one."""


def display_base(target_mask: np.ndarray, background: np.ndarray | None = None) -> np.ndarray:
    """``(H, W)`` uint8 grey image: the DSA image with vessels dark, or the mask dark on light grey."""
    if background is not None and background.shape == target_mask.shape and len(np.unique(background[::4, ::4])) > 2:
        image = background.astype(np.float32)
        low, high = np.percentile(image, (0.5, 99.5))
        if high <= low:
            low, high = float(image.min()), float(image.max())
        image = np.clip((image - low) / max(high - low, 1e-6), 0.0, 1.0)
        inside = image[target_mask].mean() if target_mask.any() else 0.0
        outside = image[~target_mask].mean() if (~target_mask).any() else 1.0
        if inside > outside:  # vessels bright (e.g. a mask or inverted DSA): show them dark
            image = 1.0 - image
        return (30 + image * (BACKGROUND_GREY - 30)).astype(np.uint8)
    return np.where(target_mask, TARGET_GREY, BACKGROUND_GREY).astype(np.uint8)


def _upscale_factor(shape: tuple[int, int], min_side: int = MIN_SIDE_PX) -> int:
    """Whole factor (1 to MAX_UPSCALE) bringing the longest side to at least ``min_side``."""
    return int(max(1, min(MAX_UPSCALE, math.ceil(min_side / max(1, max(shape))))))


def _contours(mask: np.ndarray, factor: float) -> list[np.ndarray]:
    contours, _ = cv2.findContours(mask.astype(np.uint8), cv2.RETR_LIST, cv2.CHAIN_APPROX_NONE)
    # pixel centre (i, j) sits at ((i + 0.5) k - 0.5) in the enlarged image
    return [np.round((c.astype(np.float32) + 0.5) * factor - 0.5).astype(np.int32) for c in contours]


def _font(size: int):
    from PIL import ImageFont

    try:
        return ImageFont.load_default(size=size)
    except TypeError:  # Pillow < 10.1: a fixed bitmap font
        return ImageFont.load_default()


def _scale_bar(image: np.ndarray, mm_per_px: float, font_px: int) -> None:
    """A scale bar (1, 2, 5 × 10^k mm, about a fifth of the width) at the bottom right, in place."""
    from PIL import Image, ImageDraw

    height, width = image.shape[:2]
    target_mm = 0.2 * width * mm_per_px
    if not math.isfinite(target_mm) or target_mm <= 0:
        return
    exponent = math.floor(math.log10(target_mm))
    length_mm = max(m * 10 ** exponent for m in (1, 2, 5) if m * 10 ** exponent <= target_mm)
    length_px = int(round(length_mm / mm_per_px))
    if length_px < 8:
        return
    margin = max(8, width // 40)
    thickness = max(3, height // 120)
    x1, y1 = width - margin, height - margin
    x0 = x1 - length_px
    cv2.rectangle(image, (x0 - 2, y1 - thickness - 2), (x1 + 2, y1 + 2), (255, 255, 255), -1)
    cv2.rectangle(image, (x0, y1 - thickness), (x1, y1), (0, 0, 0), -1)
    label = f"{length_mm:g} mm"
    pil = Image.fromarray(cv2.cvtColor(image, cv2.COLOR_BGR2RGB))
    draw = ImageDraw.Draw(pil)
    font = _font(font_px)
    box = draw.textbbox((0, 0), label, font=font)
    tx = x1 - (box[2] - box[0])
    ty = y1 - thickness - 6 - (box[3] - box[1]) - box[1]
    draw.text((tx, ty), label, font=font, fill=(0, 0, 0), stroke_width=2, stroke_fill=(255, 255, 255))
    image[:] = cv2.cvtColor(np.asarray(pil), cv2.COLOR_RGB2BGR)


def _caption_band(width: int, caption: Caption, font_px: int, on_image: bool = False) -> np.ndarray:
    """The band under the image: title line (view, Dice, verdict), a legend line, job/stage line."""
    from PIL import Image, ImageDraw

    pad = max(6, font_px // 2)
    line = int(font_px * 1.35)
    lines = 2 + (1 if (caption.job or caption.stage or caption.frame) else 0)
    band = Image.new("RGB", (width, pad * 2 + line * lines), CAPTION_BG[::-1])
    draw = ImageDraw.Draw(band)
    font = _font(font_px)
    bold = _font(int(font_px * 1.1))
    x, y = pad, pad
    # line 1: view · Dice · verdict
    pieces: list[tuple[str, tuple[int, int, int], object]] = []
    if caption.view:
        pieces.append((caption.view.upper(), (255, 255, 255), bold))
    if caption.dice is not None and math.isfinite(caption.dice):
        pieces.append((f"{caption.dice_label} {caption.dice:.3f}", (255, 255, 255), font))
    if caption.verdict:
        colour = (255, 255, 255) if caption.ok is None else (GOOD_RGB if caption.ok else BAD_RGB)
        pieces.append((caption.verdict, colour, bold))
    for index, (text, colour, face) in enumerate(pieces):
        if index:
            draw.text((x, y), "  ·  ", font=font, fill=(170, 170, 170))
            x += draw.textlength("  ·  ", font=font)
        draw.text((x, y), text, font=face, fill=colour)
        x += draw.textlength(text, font=face)
    # line 2: legend
    y += line
    x = pad
    swatch = max(8, font_px - 2)
    target = ("DSA image", (60, 60, 60)) if on_image else ("target vessels", (TARGET_GREY,) * 3)
    entries = [(target[0], target[1], True), ("initial", INITIAL_BGR[::-1], False), (caption.final_label, FINAL_BGR[::-1], False)]
    if caption.unmatched_label:
        entries.append((caption.unmatched_label, UNMATCHED_BGR[::-1], True))
    for label, colour, filled in entries:
        top = y + (font_px - swatch) // 2 + 2
        if filled:
            draw.rectangle((x, top, x + swatch, top + swatch), fill=colour, outline=(220, 220, 220))
        else:
            draw.line((x, top + swatch // 2, x + swatch * 2, top + swatch // 2), fill=colour, width=max(2, font_px // 6))
            x += swatch
        draw.text((x + swatch + 5, y), label, font=font, fill=(230, 230, 230))
        x += swatch + 5 + draw.textlength(label, font=font) + 2 * pad
    # line 3: job / stage
    if caption.job or caption.stage or caption.frame:
        y += line
        text = "   ".join(t for t in (caption.stage, caption.frame, caption.job) if t)
        draw.text((pad, y), text, font=font, fill=(200, 200, 200))
    return cv2.cvtColor(np.asarray(band), cv2.COLOR_RGB2BGR)


def crop_box(masks: list[np.ndarray], margin: float = 0.12, min_fraction: float = 0.35) -> tuple[int, int, int, int]:
    """``(x0, y0, x1, y1)`` around everything in ``masks`` plus a margin, square where the image
    allows, at least ``min_fraction`` of the image side; the whole image when the masks are empty."""
    height, width = masks[0].shape
    union = np.zeros((height, width), bool)
    for mask in masks:
        if mask is not None:
            union |= mask.astype(bool)
    if not union.any():
        return 0, 0, width, height
    rows, cols = np.nonzero(union)
    cy, cx = (rows.min() + rows.max()) / 2, (cols.min() + cols.max()) / 2
    side = max(rows.max() - rows.min(), cols.max() - cols.min()) * (1 + 2 * margin)
    side = int(round(max(side, min_fraction * max(height, width), 16)))
    w, h = min(side, width), min(side, height)
    x0 = int(np.clip(round(cx - w / 2), 0, width - w))
    y0 = int(np.clip(round(cy - h / 2), 0, height - h))
    return x0, y0, x0 + w, y0 + h


def overlay_image(
    target_mask: np.ndarray,
    initial: np.ndarray,
    final: np.ndarray,
    background: np.ndarray | None = None,
    *,
    caption: Caption | None = None,
    min_side: int = MIN_SIDE_PX,
    box: tuple[int, int, int, int] | None | bool = None,
    display_side: int | None = None,
    unmatched: np.ndarray | None = None,
) -> np.ndarray:
    """A BGR uint8 overlay: the region of the vessels (enlarged ×k when small), a caption band under it.

    Args:
        target_mask: ``(H, W)`` bool vessel mask the registration used.
        initial, final: ``(H, W)`` bool silhouettes, drawn as contours (blue, orange).
        background: ``(H, W)`` DSA image shown under the contours (default: the mask).
        caption: view, Dice, verdict, job, stage and the pixel size for the scale bar.
        min_side: crops whose longest side is shorter are enlarged by a whole factor (≤ 4).
        box: ``(x0, y0, x1, y1)`` region to show; None: around the target and both contours
            (:func:`crop_box`); False: the whole image.
        display_side: scale the region so its longest side has this many pixels (animation
            frames of equal size) instead of a whole enlargement factor.
        unmatched: ``(H, W)`` bool model pixels with no vessel under them (partial visibility),
            filled in magenta under the contours.
    """
    caption = caption or Caption()
    if box is None:
        box = crop_box([target_mask, initial, final])
    elif box is False:
        box = (0, 0, target_mask.shape[1], target_mask.shape[0])
    x0, y0, x1, y1 = box
    region = (slice(y0, y1), slice(x0, x1))
    target_mask = target_mask[region]
    initial = None if initial is None else initial[region]
    final = None if final is None else final[region]
    background = None if background is None else background[region]
    if display_side:
        factor = display_side / max(target_mask.shape)
    else:
        factor = _upscale_factor(target_mask.shape, min_side)
    base = display_base(target_mask, background)
    if factor != 1:
        interpolation = cv2.INTER_NEAREST if background is None and factor >= 1 else cv2.INTER_LINEAR
        size = (max(1, round(base.shape[1] * factor)), max(1, round(base.shape[0] * factor)))
        base = cv2.resize(base, size, interpolation=interpolation)
    image = cv2.cvtColor(base, cv2.COLOR_GRAY2BGR)
    if unmatched is not None and unmatched[region].any():
        fill = cv2.resize(unmatched[region].astype(np.uint8), (image.shape[1], image.shape[0]), interpolation=cv2.INTER_NEAREST) > 0
        image[fill] = (UNMATCHED_ALPHA * np.array(UNMATCHED_BGR) + (1 - UNMATCHED_ALPHA) * image[fill]).astype(np.uint8)
    height, width = image.shape[:2]
    thickness = max(1, min(max(1, round(factor)), round(max(height, width) / 400)))
    for mask, colour in ((initial, INITIAL_BGR), (final, FINAL_BGR)):
        if mask is not None and mask.any():
            cv2.drawContours(image, _contours(mask, factor), -1, colour, thickness, cv2.LINE_AA)
    font_px = max(13, min(28, width // 32))
    if caption.mm_per_px:
        _scale_bar(image, caption.mm_per_px / factor, font_px)
    on_image = background is not None and len(np.unique(background[::4, ::4])) > 2
    return np.concatenate([image, _caption_band(width, caption, font_px, on_image)], axis=0)


def write_png(path, image: np.ndarray) -> None:
    if not cv2.imwrite(str(path), image):
        raise OSError(f"could not write {path}")


def loss_plot(history: list[tuple[str, list[float]]], width: int = 800, height: int = 450) -> np.ndarray:
    """A ``(height, width, 3)`` BGR plot of the loss per iteration (see :func:`dsareg_engine.plots.loss_figure`)."""
    from .plots import loss_figure

    return loss_figure(history, width=width, height=height)
