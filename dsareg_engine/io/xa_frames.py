"""Which frames of a native run make the DSA image, and how they are combined.

Each contrast frame ``n`` is scored by its opacification ``s_n``: the integrated darkening of its
subtraction ``D_n`` beyond ``SCORE_SIGMAS`` σ, on the frames area-averaged to about 1 mm pixels
(:mod:`.xa_run_kind`), so that noise adds nothing and the scores compare across frames and pixel sizes.
The frame of maximum opacification is the *peak*; its geometry applies.

**Default: the arterial phase.** Contrast reaches the proximal vessels first and washes out of them
before the distal branches peak, so no single frame shows the whole tree. The arterial phase runs from
the first frame reaching ``ARTERIAL_FRACTION`` of the peak's opacification (before the peak) to the
last frame after the peak still above ``END_FRACTION`` of it, ending earlier where the opacification
rises again by more than ``RISE_FRACTION`` of the peak after falling (a second pass or the venous
phase). The image is the per-pixel maximum opacity over the phase: the minimum of ``D_n`` after a
running mean over ``TEMPORAL_FRAMES`` frames (each vessel pixel stays filled for a few frames; the mean
lowers the noise the minimum would otherwise pick up).

``"minip"``: the per-pixel minimum of ``D`` from the phase's first frame up to the peak (no running
mean), as before. An integer: that frame.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import DsaregInputError
from .input_decisions import InputDecision

ARTERIAL_FRACTION = 0.3
END_FRACTION = 0.25
RISE_FRACTION = 0.05
SCORE_SIGMAS = 5.0
TEMPORAL_FRAMES = 3


@dataclass(frozen=True)
class FrameChoice:
    """``geometry_frame`` (the peak, or the frame given), ``frames`` combined, ``combined`` (``"single"``,
    ``"minip"``, ``"arterial"``), ``phase`` (words, for the record) and the decision."""

    geometry_frame: int
    frames: list[int]
    combined: str
    phase: str
    decision: InputDecision


def _given(frame: int, contrast_frames: list[int], n_frames: int, field_name: str) -> int:
    if not 0 <= frame < n_frames:
        raise DsaregInputError(f"frame {frame} does not exist ({n_frames} frames)", field=field_name,
                               accepted=f"0..{n_frames - 1}, 'minip', or nothing (the arterial phase)")
    if frame not in contrast_frames:
        raise DsaregInputError(
            f"frame {frame} is not a contrast frame of the subtraction (contrast frames "
            f"{min(contrast_frames)}..{max(contrast_frames)}, 0-based)", field=field_name, accepted="a contrast frame")
    return frame


def arterial_phase(scores: dict[int, float]) -> tuple[int, int, int, str, float]:
    """``(first, peak, last, why the phase ends, the opacification after it / the peak's)``."""
    frames = sorted(scores)
    peak = max(frames, key=scores.get)
    top = max(scores[peak], 1e-12)
    first = next((n for n in frames if n <= peak and scores[n] >= ARTERIAL_FRACTION * top), peak)
    last, why, after = peak, "the run ends", 0.0
    lowest = scores[peak]
    for n in frames[frames.index(peak) + 1:]:
        after = scores[n] / top
        if after < END_FRACTION:
            why = f"opacification below {END_FRACTION:.0%} of the peak's"
            break
        if scores[n] - lowest > RISE_FRACTION * top:
            why = "opacification rises again (a second pass or the venous phase)"
            break
        last, lowest, after = n, min(lowest, scores[n]), 0.0
    return first, peak, last, why, after


def choose_frames(scores: dict[int, float], frame, n_frames: int, field_name: str) -> FrameChoice:
    """The frames for ``frame`` (``None``: the arterial phase; ``"minip"``; an index)."""
    if isinstance(frame, (int, np.integer)) and not isinstance(frame, bool):
        chosen = _given(int(frame), sorted(scores), n_frames, field_name)
        return FrameChoice(chosen, [chosen], "single", f"frame {chosen} as given", InputDecision(
            field_name, "frames combined", str(chosen), "the frame given", source="option"))
    first, peak, last, why, after = arterial_phase(scores)
    if frame == "minip":
        used = [n for n in sorted(scores) if first <= n <= peak]
        return FrameChoice(peak, used, "minip", f"MinIP from frame {first} to the peak {peak}", InputDecision(
            field_name, "frames combined", f"{first}-{peak} (minip)", "options.frames is minip", source="option"))
    used = [n for n in sorted(scores) if first <= n <= last]
    phase = (f"arterial phase: frames {first}-{last} (from {ARTERIAL_FRACTION:.0%} of the peak's opacification "
             f"to where {why}), peak {peak}, per-pixel maximum opacity")
    decision = InputDecision(field_name, "frames combined", f"{first}-{last} (arterial phase)",
                             f"opacification after the phase / the peak's ({why})", round(float(after), 3),
                             END_FRACTION)
    return FrameChoice(peak, used, "arterial", phase, decision)


def combine(images: list[np.ndarray], combined: str) -> np.ndarray:
    """One image from the frames' ``D`` ``(H, W)`` each: the frame, the MinIP, or the arterial phase's
    maximum opacity (the minimum after a running mean over ``TEMPORAL_FRAMES``)."""
    if len(images) == 1:
        return images[0]
    if combined != "arterial" or len(images) < TEMPORAL_FRAMES:
        return np.min(np.asarray(images, np.float32), axis=0)
    window = np.sum(np.asarray(images[:TEMPORAL_FRAMES], np.float64), axis=0)  # a running sum, one frame at a time
    lowest = window.copy()
    for first, last in zip(images, images[TEMPORAL_FRAMES:]):
        window += last
        window -= first
        np.minimum(lowest, window, out=lowest)
    return (lowest / TEMPORAL_FRAMES).astype(np.float32)
