"""A run's frames as an opacity stack ``(T, H, W)``: subtracted, motion-corrected, higher = more contrast.

The same subtraction registration used (:mod:`dsareg_engine.io.xa_run`), applied to every frame:

* **native run** (``image_reading.<view>.run == "native"``): in the log domain, each frame minus its mask
  (the recipe's, else the frames before contrast arrives), the mask moved by the shift registration found on
  its frame (``mask_shift_px.total_px``; the mask frames themselves are not moved); opacity ``= −D``;
* **subtracted run** (or ``subtraction: off``): the frames as stored (``MONOCHROME1`` inverted, vessels
  dark), opacity ``= −(frame − frame 0's median)``.

Each frame stands for its own acquisition time: contrast averaging of a recipe is not applied (it would blur
time). The frame times come from :mod:`.timing`; a run without them is refused.
"""

from __future__ import annotations

import io

import numpy as np

from ..io.image_io import dicom_number
from ..io.xa_recipe import parse_recipe
from ..io.xa_run import found_pairs, log_domain, recipe_pairs
from ..vision.xa_motion import shift_image
from .measure import RunFrames
from .timing import read_timing, require_timing


def _dataset(data: bytes):
    import pydicom

    return pydicom.dcmread(io.BytesIO(data), force=True)


def _stack(dataset, field_name: str) -> np.ndarray:
    stack = np.asarray(dataset.pixel_array, dtype=np.float32)
    stack = stack[None] if stack.ndim == 2 else stack
    slope = dicom_number(dataset, "RescaleSlope", 1.0, field_name, kind=float)
    intercept = dicom_number(dataset, "RescaleIntercept", 0.0, field_name, kind=float)
    return stack * slope + intercept


def native_opacity(stack: np.ndarray, dataset, shift_px: tuple[float, float], field_name: str
                   ) -> tuple[np.ndarray, list[str]]:
    """``(opacity (T, H, W), notes)`` of a native run (see the module docstring)."""
    logs, _, _ = log_domain(stack, dataset, field_name)
    items = parse_recipe(dataset, len(stack), field_name=field_name)
    pairs = recipe_pairs(items, len(stack)) if items else found_pairs(logs, field_name)[0]
    first = pairs[min(pairs)]
    masks: dict[tuple, tuple[np.ndarray, np.ndarray]] = {}  # (masks, recipe shift) → (mask, moved mask)
    out = np.empty(logs.shape, np.float32)
    for frame in range(len(logs)):
        pair = pairs.get(frame, first)
        key = (pair.masks, pair.shift_px)
        if key not in masks:
            mask = logs[list(pair.masks)].mean(axis=0)
            masks[key] = mask, shift_image(shift_image(mask, pair.shift_px), shift_px)
        mask, moved = masks[key]
        out[frame] = (mask if frame in pair.masks else moved) - logs[frame]
    notes = [f"native run: each frame minus its mask in the log domain, mask moved by ({shift_px[0]:+.2f}, "
             f"{shift_px[1]:+.2f}) px (down, right); {'recipe' if items else 'masks found'}"]
    return out, notes


def stored_opacity(stack: np.ndarray, dataset) -> np.ndarray:
    """Opacity of a run read as stored (vessels dark)."""
    if str(getattr(dataset, "PhotometricInterpretation", "")).upper() == "MONOCHROME1":
        stack = stack.max() - stack
    return (np.median(stack[0]) - stack).astype(np.float32)


def run_frames(data: bytes, field_name: str, record: dict | None) -> RunFrames:
    """The opacity stack and frame times of one view's run; ``record`` is what registration read from it
    (``result.image_reading.<view>``)."""
    dataset = _dataset(data)
    stack = _stack(dataset, field_name)
    timing = require_timing(read_timing(dataset, len(stack), field_name), len(stack), field_name)
    record = record or {}
    if record.get("run") == "native":
        total = (record.get("mask_shift_px") or {}).get("total_px") or [0.0, 0.0]
        recipe = (record.get("mask_shift_px") or {}).get("recipe_px") or [0.0, 0.0]
        found = (float(total[0]) - float(recipe[0]), float(total[1]) - float(recipe[1]))
        opacity, notes = native_opacity(stack, dataset, found, field_name)
    else:
        opacity, notes = stored_opacity(stack, dataset), ["subtracted run: frames as stored"]
    return RunFrames(opacity, timing, tuple(notes))
