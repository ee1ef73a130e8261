"""A multi-frame XA run → the one DSA image registration fits, and a record of how it was made.

**Native or subtracted** (:mod:`.xa_run_kind`). A run is *native* (stored unsubtracted; the viewer
subtracts) when it carries a Mask Subtraction Sequence (:mod:`.xa_recipe`) or Recommended Viewing
Mode (0028,1090) ``SUB``; *subtracted* when its Image Type or Derivation Description says so.
Otherwise its content decides, at a physical scale: anatomy common to the early frames far above
the frame-to-frame noise is native. Every decision is an :class:`~.input_decisions.InputDecision`
(run kind; the mask frames when no recipe names them). Subtracted runs (and ``subtraction="off"``) are
read as before: the frame of maximum vessel opacification, a given frame, or the MinIP of all frames.

**Native runs, in the log domain.** Pixel Intensity Relationship (0028,1040) ``LIN`` (values ∝
X-ray intensity): ``log(value)``; ``LOG``: the values as they are; ``DISP``: as ``LOG``, with a
warning (a display curve is not a logarithm). Its sign (0028,1041) ``−1`` (higher values = less
intensity) is turned around first, so that in the log domain more attenuation is always lower.
The DSA image of contrast frame ``n`` is ``D_n = log C_n − log M_n`` (0 where nothing changed,
negative in the vessels: vessels dark, as the readers deliver DSA), with ``M_n`` the recipe's
mask (moved by its Mask Sub-pixel Shift) or, without a recipe, the mean of the frames before
contrast arrives. The mask is then moved onto the contrast frame by the patient motion found on
the background (:mod:`dsareg_engine.vision.xa_motion`: a rotation and a shift); the move is recorded.

**Which frames** (:mod:`.xa_frames`). ``None``: the per-pixel maximum opacity over the arterial
phase (contrast washes out of the near vessels before the far ones peak); ``"minip"``: the
per-pixel minimum of ``D`` from the phase's start up to the peak; an integer: that frame (0-based).
The geometry is read from the peak frame (or the frame given) — enhanced XA stores positioner
angles per frame.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from ..errors import DsaregInputError
from ..vision.xa_motion import Motion, MotionSettings, estimate_motion, move_image, shift_image
from .input_decisions import InputDecision
from .xa_frames import SCORE_SIGMAS, choose_frames, combine
from .xa_recipe import SubtractionItem, parse_recipe
from .xa_run_kind import decide_run_kind, grid_factor, on_grid

ARRIVAL_FRACTION = 0.01
ARRIVAL_NOISE = 4.0
ARRIVAL_SIGMAS = 5.0
MOVE_MM = 0.1
CONTRAST_SIGMAS = 5.0
SUBTRACTIONS = ("auto", "off")
GRID_MOTION = MotionSettings(iterations=6, coarse_side_px=512, fine_side_px=512)
"""A frame's move on the ~1 mm grid (one level), from a phase correlation."""
GRID_STEP = MotionSettings(iterations=2, coarse_side_px=512, fine_side_px=512)
"""... from the previous frame's move instead (patients move slowly): two Gauss-Newton steps."""
PHASE_STEP = MotionSettings(iterations=2)
"""The arterial phase's other frames: the peak's move refined at the image's coarsest level (~256 px) by two
steps (measured at 512 px, 0.5° + (0.8, -0.5) px: every frame within 0.04 px of the truth, as with twelve;
a coarser level, 128 px, was 0.1 px off)."""

@dataclass(frozen=True)
class RunReading:
    """How a multi-frame run is read.

    Attributes:
        frame: ``None`` (native runs: the arterial phase; subtracted runs: maximum opacification), ``"minip"``,
            or a 0-based frame index.
        subtraction: ``"auto"``: native runs are subtracted (recipe, or masks found); ``"off"``: frames as stored.
        motion_correction: estimate and correct the mask ↔ contrast shift on native runs.
    """

    frame: int | str | None = None
    subtraction: str = "auto"
    motion_correction: bool = True


@dataclass(frozen=True)
class ImageReading:
    """How a case's two images are read: a frame choice per view, and the subtraction settings.

    Attributes:
        ap_frame, lat_frame: per view, as :attr:`RunReading.frame`.
        subtraction, motion_correction: as in :class:`RunReading`, for both views.
    """

    ap_frame: int | str | None = None
    lat_frame: int | str | None = None
    subtraction: str = "auto"
    motion_correction: bool = True

    @classmethod
    def both(cls, frame: int | str | None) -> ImageReading:
        return cls(ap_frame=frame, lat_frame=frame)

    def for_view(self, name: str) -> RunReading:
        return RunReading(frame=getattr(self, f"{name}_frame", None), subtraction=self.subtraction,
                          motion_correction=self.motion_correction)

    def merged(self, other: ImageReading | None, field_prefix: str = "options.frames") -> ImageReading:
        """``other``'s frames where this one has none (a frame given twice, differently, is refused);
        ``other``'s subtraction settings."""
        if other is None:
            return self
        frames = {}
        for name in ("ap", "lat"):
            mine, theirs = getattr(self, f"{name}_frame"), getattr(other, f"{name}_frame")
            if mine is not None and theirs is not None and mine != theirs:
                raise DsaregInputError(f"the {name} frame is given twice ({mine!r} and {theirs!r})",
                                       field=f"{field_prefix}.{name}", accepted="one frame choice per view")
            frames[f"{name}_frame"] = mine if mine is not None else theirs
        return ImageReading(**frames, subtraction=other.subtraction, motion_correction=other.motion_correction)


@dataclass
class RunImage:
    """The image made from a run: ``pixels`` ``(H, W)`` float32, the frame whose geometry applies,
    ``record`` (JSON-ready: what was read and done), warnings and the decisions taken."""

    pixels: np.ndarray
    geometry_frame: int | None
    record: dict
    warnings: list[str] = field(default_factory=list)
    decisions: list[InputDecision] = field(default_factory=list)


# ---- native or subtracted (:mod:`.xa_run_kind`) ----------------------------------------------------


def _robust_std(values: np.ndarray) -> float:
    values = values.ravel()
    return float(1.4826 * np.median(np.abs(values - np.median(values))))


def run_kind(dataset, stack: np.ndarray, field_name: str = "image") -> tuple[str, str]:
    """``("native" | "subtracted", why)`` (:func:`.xa_run_kind.decide_run_kind`)."""
    kind, why, _ = decide_run_kind(dataset, stack, field_name)
    return kind, why


# ---- the log domain --------------------------------------------------------------------------------


def log_domain(stack: np.ndarray, dataset, field_name: str) -> tuple[np.ndarray, dict, list[str]]:
    """``(log-intensity stack, {"relationship", "sign"}, warnings)``; ``stack`` after the rescale."""
    from .dicom_xa import find_tag  # top level, else the (enhanced XA) functional groups

    warnings: list[str] = []
    relationship = str(find_tag(dataset, "PixelIntensityRelationship") or "").strip().upper()
    if relationship not in ("LIN", "LOG", "DISP"):
        warnings.append(f"{field_name}: Pixel Intensity Relationship is '{relationship[:8] or 'missing'}'; "
                        "read as LIN (values proportional to X-ray intensity)")
        relationship = "LIN"
    sign_value = find_tag(dataset, "PixelIntensityRelationshipSign")
    monochrome1 = str(getattr(dataset, "PhotometricInterpretation", "")).upper() == "MONOCHROME1"
    sign = int(sign_value) if sign_value in (1, -1) else (-1 if monochrome1 else 1)
    if relationship == "DISP":
        warnings.append(f"{field_name}: Pixel Intensity Relationship DISP (display values): subtracted as if LOG")
    if relationship == "LIN":
        top = float(2 ** int(getattr(dataset, "BitsStored", 16) or 16) - 1)
        intensity = stack if sign > 0 else top - stack
        logs = np.log(np.maximum(intensity, 1.0)).astype(np.float32)
    else:
        logs = (stack if sign > 0 else -stack).astype(np.float32)
    return logs, {"pixel_intensity_relationship": relationship, "sign": sign}, warnings


# ---- masks ----------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Pair:
    """What frame ``frame`` is subtracted with: contrast frames averaged, mask frames averaged, mask shift."""

    frame: int
    contrast: tuple[int, ...]
    masks: tuple[int, ...]
    shift_px: tuple[float, float] = (0.0, 0.0)


def recipe_pairs(items: list[SubtractionItem], n_frames: int) -> dict[int, Pair]:
    """Every frame the recipe subtracts (the first item naming a frame wins)."""
    pairs: dict[int, Pair] = {}
    for item in items:
        for frame in item.frames:
            masks = item.mask_of(frame)
            if frame in pairs or not masks or frame in masks or not all(0 <= m < n_frames for m in masks):
                continue
            last = min(frame + item.contrast_averaging, item.frames[-1] + 1, n_frames)
            pairs[frame] = Pair(frame, tuple(range(frame, last)), masks, item.mask_shift_px)
    return pairs


def opacification(difference: np.ndarray, sigmas: float = 3.0) -> float:
    """Integrated darkening beyond the noise: ``Σ max(0, −D − k σ)`` (σ: robust spread of ``D``, k = ``sigmas``)."""
    sigma = _robust_std(difference)
    return float(np.maximum(0.0, -difference - sigmas * sigma).sum())


def _moved_px(first: np.ndarray, frame: np.ndarray) -> float:
    """How far ``frame`` moved from ``first`` (grid px): the shift plus the rotation's move at the image edge."""
    motion = estimate_motion(first, frame, GRID_MOTION)
    return float(np.abs(motion.shift_px).max() + abs(np.radians(motion.rotation_deg)) * max(first.shape) / 2.0)


def found_pairs(logs: np.ndarray, field_name: str, grid_factor: int = 1, move_px: float = 0.1
                ) -> tuple[dict[int, Pair], int, InputDecision]:
    """No recipe: the mask is the mean of the frames before anything changes; ``(pairs, arrival, decision)``.

    On the frames area-averaged by ``grid_factor`` (about 1 mm pixels, :mod:`.xa_run_kind`: the noise
    averaged out, the vessels kept), each frame's darkening against frame 0 beyond ``ARRIVAL_SIGMAS`` σ
    is measured. Contrast has arrived in the first frame whose darkening exceeds both
    ``ARRIVAL_FRACTION`` of the peak's and ``ARRIVAL_NOISE`` times the quietest frame's; an earlier
    frame that moved more than ``move_px`` (grid px, :mod:`dsareg_engine.vision.xa_motion`) from frame
    0 ends the masks there. The decision's measure is the last mask frame's darkening over its
    threshold or its move over ``move_px``, the larger (close to 1: the mask may hold contrast or motion)."""
    small = np.array([on_grid(frame, grid_factor) for frame in logs])
    scores = np.array([0.0] + [opacification(small[n] - small[0], ARRIVAL_SIGMAS) for n in range(1, len(small))])
    if scores.max() <= 0:
        raise DsaregInputError("no frame of the native run shows contrast (every frame looks like the first)",
                               field=field_name, accepted="a run whose later frames show contrast-filled vessels")
    quiet = float(scores[1:].min())  # the quietest frame: noise (and motion) only
    threshold = max(ARRIVAL_FRACTION * scores.max(), ARRIVAL_NOISE * quiet)
    arrival, measure = max(1, int(np.argmax(scores > threshold))), 0.0
    for n in range(1, arrival):
        moved = _moved_px(small[0], small[n]) / move_px
        if moved > 1.0:
            arrival = n
            break
        measure = max(moved, float(scores[n] / max(threshold, 1e-12)))
    masks = tuple(range(arrival))
    decision = InputDecision(field_name, "mask frames", ",".join(str(m) for m in masks),
                             "contrast or motion in the last mask frame / the arrival threshold",
                             round(measure, 3), 1.0, 0.5)
    return {n: Pair(n, (n,), masks) for n in range(arrival, len(logs))}, arrival, decision


def _difference(logs: np.ndarray, pair: Pair, step: int = 1) -> np.ndarray:
    contrast = logs[list(pair.contrast), ::step, ::step].mean(axis=0)
    mask = logs[list(pair.masks), ::step, ::step].mean(axis=0)
    shift = (pair.shift_px[0] / step, pair.shift_px[1] / step)
    return contrast - shift_image(mask, shift)


# ---- one image from the run ---------------------------------------------------------------------------


def net_opacification(difference: np.ndarray, sigmas: float) -> float:
    """Darkening beyond ``sigmas`` σ minus brightening beyond it (≥ 0): contrast only darkens, while an
    uncorrected move darkens one side of an edge and brightens the other, and cancels."""
    sigma = _robust_std(difference)
    dark = np.maximum(0.0, -difference - sigmas * sigma).sum()
    bright = np.maximum(0.0, difference - sigmas * sigma).sum()
    return float(max(0.0, dark - bright))


def _frame_scores(logs: np.ndarray, pairs: dict[int, Pair], factor: int, motion_correction: bool = True
                  ) -> dict[int, float]:
    """Each contrast frame's net opacification on the ~1 mm grid (:mod:`.xa_frames`), the mask moved by
    the recipe's shift and the motion found there (a move left in would count as contrast)."""
    small = np.array([on_grid(frame, factor) for frame in logs])
    scores, previous = {}, None
    for n, pair in pairs.items():
        contrast = small[list(pair.contrast)].mean(axis=0)
        mask = shift_image(small[list(pair.masks)].mean(axis=0), (pair.shift_px[0] / factor, pair.shift_px[1] / factor))
        if motion_correction:  # from the previous frame's move when there is one (patients move slowly)
            settings = GRID_MOTION if previous is None or previous.none else GRID_STEP
            motion = previous = estimate_motion(mask, contrast, settings, previous)
            mask = move_image(mask, motion.shift_px, motion.rotation_deg)
        scores[n] = net_opacification(contrast - mask, SCORE_SIGMAS)
    return scores


def _corrected(logs: np.ndarray, pair: Pair, reading: RunReading, warnings: list[str], field_name: str,
               start: Motion | None = None) -> tuple[np.ndarray, dict, Motion]:
    """``D`` of one pair with the mask moved by the recipe's shift and the rigid motion found (refined from
    ``start`` at the finest level when given); the move, as recorded and as found."""
    contrast = logs[list(pair.contrast)].mean(axis=0)
    mask = shift_image(logs[list(pair.masks)].mean(axis=0), pair.shift_px)
    found = Motion()
    if reading.motion_correction:
        found = estimate_motion(mask, contrast, MotionSettings() if start is None else PHASE_STEP, start)
        if found.none:
            warnings.append(f"{field_name}: no patient motion could be estimated for frame {pair.frame}")
        mask = move_image(mask, found.shift_px, found.rotation_deg)
    total = (pair.shift_px[0] + found.shift_px[0], pair.shift_px[1] + found.shift_px[1])
    move = {"recipe_px": [round(v, 4) for v in pair.shift_px], "found_px": [round(v, 4) for v in found.shift_px],
            "total_px": [round(v, 4) for v in total], "rotation_deg": round(found.rotation_deg, 4)}
    return (contrast - mask).astype(np.float32), move, found


def _check_run_contrast(scores: dict[int, float], field_name: str) -> None:
    """A run none of whose frames darkens beyond the noise once its mask is subtracted (the motion corrected) shows
    no contrast, whatever frame is asked for: refused for every frame choice alike."""
    if not scores or max(scores.values()) <= 0.0:
        raise DsaregInputError(
            f"no contrast found: no frame of the run darkens beyond {SCORE_SIGMAS:g} sigma of the noise once its "
            "mask is subtracted (what changes is brightness or motion, not contrast filling vessels)",
            field=field_name, accepted="a run with contrast-filled vessels in its contrast frames")


def _check_contrast(image: np.ndarray, field_name: str, frames: list[int]) -> None:
    sigma = _robust_std(image)
    smooth = cv2.GaussianBlur(image, (0, 0), 1.0)
    dark = int((smooth < -CONTRAST_SIGMAS * max(sigma, 1e-6) / 2.0).sum())
    if dark < max(20, int(5e-4 * image.size)):
        raise DsaregInputError(
            f"no contrast found: the subtracted frame {frames[-1]} shows no vessels above the noise",
            field=field_name, accepted="a run with contrast-filled vessels in its contrast frames")


def subtraction_pairs(logs: np.ndarray, dataset, field_name: str
                      ) -> tuple[dict[int, Pair], list[str] | str, InputDecision | None]:
    """What each frame of a native run (``logs`` ``(N, H, W)``) is subtracted with: ``(pairs, the recipe as
    recorded, the mask-frames decision)``: the file's recipe, else the masks found on the ~1 mm grid
    (:func:`found_pairs`; no decision with a recipe). Registration's reading and hemodynamics both use it."""
    items = parse_recipe(dataset, len(logs), field_name=field_name)
    if items:
        pairs = recipe_pairs(items, len(logs))
        if not pairs:
            raise DsaregInputError("the Mask Subtraction Sequence subtracts no frame", field=f"{field_name}.MaskSubtractionSequence")
        return pairs, [item.describe() for item in items], None
    factor, grid_mm = grid_factor(dataset, logs.shape[1:])
    pairs, arrival, found = found_pairs(logs, field_name, factor, MOVE_MM / grid_mm)
    return pairs, f"none in the file: mask = the frames before contrast arrives (frame index {arrival})", found


def read_native(stack: np.ndarray, dataset, reading: RunReading, why: str, field_name: str) -> RunImage:
    """The DSA image of a native run (see the module docstring)."""
    logs, intensity, warnings = log_domain(stack, dataset, field_name)
    record: dict = {"frames": len(stack), "run": "native", "why": why, **intensity}
    factor, _ = grid_factor(dataset, stack.shape[1:])
    pairs, record["recipe"], found = subtraction_pairs(logs, dataset, field_name)
    decisions: list[InputDecision] = [found] if found is not None else []
    scores = _frame_scores(logs, pairs, factor, reading.motion_correction)
    _check_run_contrast(scores, field_name)
    choice = choose_frames(scores, reading.frame, len(stack), field_name)
    decisions.append(choice.decision)
    geometry_frame, used = choice.geometry_frame, choice.frames
    moves: dict[int, dict] = {}
    image, moves[geometry_frame], peak_motion = _corrected(logs, pairs[geometry_frame], reading, warnings, field_name)
    _check_contrast(image, field_name, [geometry_frame])  # the peak (or the frame given), not a MinIP of noise
    images = [(geometry_frame, image)]
    for frame in [f for f in used if f != geometry_frame]:  # each from the peak's move, refined coarsely
        image, moves[frame], _ = _corrected(logs, pairs[frame], reading, warnings, field_name, peak_motion)
        images.append((frame, image))
    pixels = combine([image for _, image in sorted(images, key=lambda item: item[0])], choice.combined)
    pair = pairs[geometry_frame]
    record.update({
        "frame_index": geometry_frame, "frame_number": geometry_frame + 1,
        "combined": choice.combined, "phase": choice.phase,
        "frame_indices": used, "mask_frame_indices": list(pair.masks),
        "mask_frame_numbers": [m + 1 for m in pair.masks], "contrast_frame_indices": list(pair.contrast),
        "mask_shift_px": moves[geometry_frame], "motion_correction": reading.motion_correction,
        "shift_convention": "mask moved by the recipe's shift, turned by rotation_deg about the image centre "
                            "(counter-clockwise as displayed), then moved by found_px (down, right) onto the contrast frame",
    })
    if len(used) > 1:
        record["mask_shift_px_per_frame"] = {str(f): moves[f]["total_px"] for f in used}
    text = choice.phase if len(used) > 1 else f"frame {geometry_frame}"
    move = moves[geometry_frame]["total_px"]
    turn = moves[geometry_frame]["rotation_deg"]
    warnings.append(f"{field_name}: native run of {len(stack)} frames ({why}): {text} minus mask frame(s) "
                    f"{', '.join(str(m) for m in pair.masks)} in the log domain, mask moved by "
                    f"({move[0]:+.2f}, {move[1]:+.2f}) px (down, right) and turned {turn:+.2f} deg "
                    "(0-based frame indices)")
    return RunImage(pixels, geometry_frame, record, warnings, decisions)


@dataclass(frozen=True)
class RunKindCall:
    """How a run is taken: ``kind`` (``"native"``, ``"subtracted"``, ``"single frame"``), ``why``, and the
    decision (``None`` for a single frame)."""

    kind: str
    why: str
    decision: InputDecision | None = None


def classify_run(stack: np.ndarray, dataset, reading: RunReading, field_name: str) -> RunKindCall:
    """Native or subtracted (``subtraction="off"``: subtracted, as the user said)."""
    if reading.subtraction not in SUBTRACTIONS:
        raise DsaregInputError(f"subtraction '{reading.subtraction}' is not understood",
                               field="options.subtraction", accepted=", ".join(SUBTRACTIONS))
    if len(stack) < 2:
        return RunKindCall("single frame", "single frame")
    if reading.subtraction == "off":
        return RunKindCall("subtracted", "read as stored", InputDecision(
            field_name, "run kind", "subtracted", "options.subtraction is off", source="option"))
    kind, why, decision = decide_run_kind(dataset, stack, field_name)
    return RunKindCall(kind, why, decision)


def read_run(stack: np.ndarray, dataset, reading: RunReading, field_name: str) -> tuple[RunImage | None, RunKindCall]:
    """``(a native run's DSA image or None for a subtracted run (read as stored by the caller), the call)``;
    the image's ``decisions`` start with the run-kind decision.

    ``stack``: ``(N, H, W)`` after the rescale, before any MONOCHROME1 inversion.
    """
    call = classify_run(stack, dataset, reading, field_name)
    if call.kind != "native":
        return None, call
    image = read_native(stack, dataset, reading, call.why, field_name)
    image.decisions.insert(0, call.decision)
    return image, call


def subtracted_record(n_frames: int, chosen: int | None, frame, why: str, kind: str = "subtracted") -> dict:
    """The record of a run read as stored (``kind`` ``"unsubtracted"``: a native run whose recipe says NONE)."""
    run = ("unsubtracted" if kind == "unsubtracted" else "subtracted") if n_frames > 1 else "single frame"
    record: dict = {"frames": n_frames, "run": run, "why": why}
    if frame == "minip":
        record.update({"combined": "minip", "frame_indices": list(range(n_frames))})
    elif chosen is not None:
        record.update({"frame_index": chosen, "frame_number": chosen + 1, "combined": "single"})
    return record
