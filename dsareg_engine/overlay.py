"""Overlay images: target mask with the initial and final silhouette contours, and a legend."""

from __future__ import annotations

import cv2
import numpy as np

TARGET_GREY = 90
INITIAL_BGR = (0, 165, 255)  # orange
FINAL_BGR = (80, 220, 0)  # green


def overlay_image(target_mask: np.ndarray, initial: np.ndarray, final: np.ndarray, background: np.ndarray | None = None) -> np.ndarray:
    """A ``(H, W, 3)`` uint8 BGR overlay.

    Args:
        target_mask: ``(H, W)`` bool, drawn in grey (or over ``background``, a ``(H, W)`` image).
        initial, final: ``(H, W)`` bool silhouettes, drawn as contours.
    """
    if background is not None:
        base = cv2.normalize(background.astype(np.float32), None, 0, 255, cv2.NORM_MINMAX).astype(np.uint8)
    else:
        base = np.where(target_mask, TARGET_GREY, 0).astype(np.uint8)
    image = cv2.cvtColor(base, cv2.COLOR_GRAY2BGR)
    thickness = max(1, round(min(target_mask.shape) / 400))
    for mask, colour in ((initial, INITIAL_BGR), (final, FINAL_BGR)):
        contours, _ = cv2.findContours(mask.astype(np.uint8), cv2.RETR_LIST, cv2.CHAIN_APPROX_NONE)
        cv2.drawContours(image, contours, -1, colour, thickness)
    _legend(image)
    return image


def _legend(image: np.ndarray) -> None:
    scale = max(0.35, min(image.shape[:2]) / 1000)
    entries = (("target", (TARGET_GREY,) * 3), ("initial", INITIAL_BGR), ("registered", FINAL_BGR))
    step = int(22 * scale / 0.5)
    for row, (label, colour) in enumerate(entries):
        y = step * (row + 1)
        cv2.rectangle(image, (8, y - step // 2), (8 + step // 2, y), colour, -1)
        cv2.putText(image, label, (14 + step // 2, y), cv2.FONT_HERSHEY_SIMPLEX, scale, (255, 255, 255), 1, cv2.LINE_AA)


def write_png(path, image: np.ndarray) -> None:
    if not cv2.imwrite(str(path), image):
        raise OSError(f"could not write {path}")


def loss_plot(history: list[tuple[str, list[float]]], width: int = 640, height: int = 360) -> np.ndarray:
    """A ``(height, width, 3)`` BGR plot of the loss per iteration (log scale), one colour per stage."""
    image = np.full((height, width, 3), 255, np.uint8)
    values = [v for _, losses in history for v in losses if v > 0 and np.isfinite(v)]
    if not values:
        return image
    low, high = np.log10(min(values)), np.log10(max(values))
    span = max(high - low, 1e-6)
    total = sum(len(losses) for _, losses in history)
    margin = 40
    colours = [(180, 119, 31), (14, 127, 255), (44, 160, 44), (40, 39, 214), (189, 103, 148), (75, 86, 140)]
    start = 0
    for index, (name, losses) in enumerate(history):
        points = [
            (margin + int((start + i) / max(total - 1, 1) * (width - 2 * margin)),
             height - margin - int((np.log10(v) - low) / span * (height - 2 * margin)))
            for i, v in enumerate(losses) if v > 0 and np.isfinite(v)
        ]
        colour = colours[index % len(colours)]
        if len(points) > 1:
            cv2.polylines(image, [np.array(points, np.int32)], False, colour, 2, cv2.LINE_AA)
        cv2.putText(image, name, (margin + 5, 18 + 16 * index), cv2.FONT_HERSHEY_SIMPLEX, 0.45, colour, 1, cv2.LINE_AA)
        start += len(losses)
    cv2.rectangle(image, (margin, margin), (width - margin, height - margin), (0, 0, 0), 1)
    cv2.putText(image, f"loss (log) {10 ** high:.2e}", (width - 220, margin - 6), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (0, 0, 0), 1)
    cv2.putText(image, f"{10 ** low:.2e}", (width - 120, height - margin + 16), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (0, 0, 0), 1)
    cv2.putText(image, "iteration", (width // 2 - 30, height - 10), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 0), 1)
    return image
