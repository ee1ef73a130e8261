"""A run's frames as an opacity stack ``(T, H, W)``: subtracted, motion-corrected, higher = more contrast.

The same subtraction registration used (:mod:`dsareg_engine.io.xa_run`), applied to every frame:

* **native run** (``image_reading.<view>.run == "native"``): in the log domain, each frame minus its mask
  (the recipe's, else the frames before contrast arrives, found as registration found them:
  :func:`dsareg_engine.io.xa_run.subtraction_pairs`, on the ~1 mm grid), the mask moved by the recipe's shift
  and then by the rigid move registration found on its frame (``mask_shift_px.found_px`` and ``rotation_deg``;
  the mask frames themselves are not moved); opacity ``= −D``;
* **subtracted run** (or ``subtraction: off``): the frames as stored (``MONOCHROME1`` inverted, vessels
  dark), opacity ``= −(frame − frame 0's median)``.

Each frame stands for its own acquisition time: contrast averaging of a recipe is not applied (it would blur
time). The frame times come from :mod:`.timing`; a run without them is refused.
"""

from __future__ import annotations

import io

import numpy as np

from ..io.image_io import dicom_number
from ..io.xa_run import Pair, log_domain, subtraction_pairs
from ..vision.xa_motion import Motion, move_image, shift_image
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


def recorded_pairs(record: dict, n_frames: int) -> dict[int, Pair] | None:
    """The subtraction registration found for a run without a recipe (every frame from contrast arrival on minus
    the mean of the frames before it), rebuilt from its record (``recipe`` a sentence, ``mask_frame_indices``
    0 … k − 1) rather than found again: the same pairs :func:`dsareg_engine.io.xa_run.found_pairs` gives on the
    same frames. ``None`` when the record does not say so (a recipe, or no record)."""
    masks = record.get("mask_frame_indices")
    if not isinstance(record.get("recipe"), str) or not masks or list(masks) != list(range(len(masks))) \
            or len(masks) >= n_frames:
        return None
    masks = tuple(int(m) for m in masks)
    return {n: Pair(n, (n,), masks) for n in range(len(masks), n_frames)}


def native_opacity(stack: np.ndarray, dataset, motion: Motion, field_name: str, record: dict | None = None
                   ) -> tuple[np.ndarray, list[str]]:
    """``(opacity (T, H, W), notes)`` of a native run (see the module docstring); ``motion``: the rigid move
    registration found on its frame (after the recipe's shift); ``record``: registration's reading of the run
    (its masks are reused where it found them, :func:`recorded_pairs`)."""
    logs, _, _ = log_domain(stack, dataset, field_name)
    pairs = recorded_pairs(record or {}, len(logs))
    recipe = (record or {}).get("recipe")
    if pairs is None:
        pairs, recipe, _ = subtraction_pairs(logs, dataset, field_name)
    first = pairs[min(pairs)]
    masks: dict[tuple, tuple[np.ndarray, np.ndarray]] = {}  # (masks, recipe shift) → (mask, moved mask)
    out = np.empty(logs.shape, np.float32)
    for frame in range(len(logs)):
        pair = pairs.get(frame, first)
        key = (pair.masks, pair.shift_px)
        if key not in masks:
            mask = logs[list(pair.masks)].mean(axis=0)
            masks[key] = mask, move_image(shift_image(mask, pair.shift_px), motion.shift_px, motion.rotation_deg)
        mask, moved = masks[key]
        out[frame] = (mask if frame in pair.masks else moved) - logs[frame]
    notes = [f"native run: each frame minus its mask in the log domain, mask moved by ({motion.shift_px[0]:+.2f}, "
             f"{motion.shift_px[1]:+.2f}) px (down, right) and turned {motion.rotation_deg:+.2f} deg; "
             f"{'recipe' if isinstance(recipe, list) else 'masks found on the ~1 mm grid'}"]
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
        move = record.get("mask_shift_px") or {}
        found = move.get("found_px") or [0.0, 0.0]
        motion = Motion((float(found[0]), float(found[1])), float(move.get("rotation_deg") or 0.0))
        opacity, notes = native_opacity(stack, dataset, motion, field_name, record)
    else:
        opacity, notes = stored_opacity(stack, dataset), ["subtracted run: frames as stored"]
    return RunFrames(opacity, timing, tuple(notes))
