"""How each input was read: image readings, mask shifts, volumes, the input decisions, the acquisition
(runs acquired together or not)."""

from __future__ import annotations

from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field

from .closed import CLOSED
from .result_metrics import Matrix4, Motion



class MaskShift(BaseModel):
    """How far the mask was moved onto the contrast frame, ``[down, right]`` px."""

    model_config = CLOSED

    recipe_px: list[float] = Field(description="From the run's Mask Sub-pixel Shift (0 when it has none).")
    found_px: list[float] = Field(description="The patient motion measured on the background.")
    total_px: list[float] = Field(description="Applied in all (recipe + found).")
    rotation_deg: float | None = Field(None, description="The patient rotation measured with found_px, about the "
                                       "image centre, counter-clockwise as displayed (applied after the recipe's shift).")


class ImageReadingRecord(BaseModel):
    """What was read from one multi-frame XA run (frame indices are 0-based, frame numbers 1-based as in DICOM)."""

    model_config = ConfigDict(CLOSED, json_schema_extra={"examples": [{
        "frames": 10, "run": "native", "why": "it carries a Mask Subtraction Sequence",
        "pixel_intensity_relationship": "LIN", "sign": 1,
        "recipe": [{"operation": "AVG_SUB", "frames": "3-10", "mask_frame_numbers": [1, 2]}],
        "frame_index": 7, "frame_number": 8, "combined": "single", "frame_indices": [7],
        "mask_frame_indices": [0, 1], "mask_frame_numbers": [1, 2],
        "mask_shift_px": {"recipe_px": [0, 0], "found_px": [0.45, -0.41], "total_px": [0.45, -0.41]}}]})

    frames: int = Field(description="Frames in the run.")
    run: Literal["native", "subtracted", "unsubtracted", "single frame"] = Field(
        description="native: stored unsubtracted and subtracted here; subtracted: read as stored; unsubtracted: its "
                    "Mask Subtraction Sequence says NONE (no subtraction), read as stored.")
    why: str = Field(description="What told native from subtracted (tags, or the content).")
    frame_index: int | None = Field(None, description="The frame used (a MinIP: the peak frame, whose geometry applies).")
    frame_number: int | None = Field(None, description="The same, 1-based.")
    combined: Literal["single", "minip", "arterial"] | None = Field(
        None, description="One frame, a MinIP of frame_indices, or (native runs' default) the per-pixel maximum "
                          "opacity over the arterial phase frame_indices.")
    phase: str | None = Field(None, description="Native runs: which frames were combined and why, in words.")
    frame_indices: list[int] | None = Field(None, description="The frames combined.")
    mask_frame_indices: list[int] | None = Field(None, description="Native runs: the mask frames subtracted.")
    mask_frame_numbers: list[int] | None = Field(None, description="The same, 1-based.")
    recipe: Any | None = Field(None, description="Native runs: the Mask Subtraction Sequence items as read, or how "
                               "the mask was found without one.")
    pixel_intensity_relationship: str | None = Field(None, description="LIN, LOG or DISP, as read.")
    sign: int | None = Field(None, description="Pixel Intensity Relationship Sign as applied.")
    mask_shift_px: MaskShift | None = None
    contrast_frame_indices: list[int] | None = Field(None, description="Native runs: the contrast frames averaged "
                                                     "for the frame used (the recipe's Contrast Frame Averaging).")
    motion_correction: bool | None = Field(None, description="Native runs: whether patient motion was corrected.")
    shift_convention: str | None = Field(None, description="How the mask was moved onto the contrast frame, in words.")
    mask_shift_px_per_frame: dict[str, list[float]] | None = Field(
        None, description="Combined frames: per frame index, the total shift [down, right] px of its mask.")


class VolumeRead(BaseModel):
    """What was read from a volume input: its kind, the vessel window, the voxels kept."""

    model_config = CLOSED

    kind: Literal["cta", "mra", "3d-dsa", "labels"] = Field(description="How the volume was read (labels: a label "
                                                                     "map or 0/1 mask, read as its labels).")
    kind_source: str = Field(description="Why: the DICOM tags / values that decided, or `options.volume_kind`.")
    unit: Literal["HU", "intensity", "label"]
    vessel_min: float = Field(description="Lowest vessel value kept (HU or intensity).")
    vessel_max: float | None = Field(None, description="CTA: the bone level (HU); voxels above it are bone.")
    tissue_level: float | None = Field(None, description="Estimated background tissue level.")
    vessel_level: float | None = Field(None, description="Estimated vessel level.")
    voxels_kept: int = Field(description="Vessel voxels kept.")
    voxels_total: int = Field(description="Voxels in the volume.")
    components: int = Field(description="Connected vessel components kept.")
    surface: str = Field("level", description="`level` (at vessel_min) or `local half maximum` (MRA).")
    faces: int = Field(description="Faces of the extracted surface, before decimation to the working budget.")
    plate_share: float | None = Field(None, description="Plate share of the kept voxels' medial axis, measured in mm "
                                      "(vessels about 0-0.25, bone plates 0.6-1; refused above 0.5, a close call from 0.35).")
    labels: list[int] | None = Field(None, description="A label map: the labels read as vessels (options.volume_labels, "
                                     "else every label above 0).")


class InputDecisionRecord(BaseModel):
    """One decision about an input (`dsareg_engine.io.input_decisions`): what was decided, on which measure, and
    how close the call was. A close call (`close`) makes the verdict at least `check`, with a reason."""

    model_config = CLOSED

    input: str = Field(description="`ap`, `lat`, `mesh` or `volume`.")
    what: str = Field(description="What was decided, e.g. `run kind`, `units`, `volume kind`, `handedness`.")
    chosen: str = Field(description="The outcome, e.g. `native`, `mm`, `cta`.")
    basis: str = Field(description="What the measure is, in words.")
    measure: float | None = Field(None, description="The number decided on; null for a tag or an option.")
    threshold: float | None = Field(None, description="Where the decision turns, in the measure's units.")
    band: float | None = Field(None, description="Half-width of the close-call band around the threshold.")
    margin: float | None = Field(None, description="measure − threshold.")
    close: bool = Field(description="|margin| < band: a close call (the verdict is at least `check`).")
    source: Literal["measured", "tag", "option"] = Field(description="Measured, read from a tag, or given.")


class Acquisition(BaseModel):
    """Whether the AP and LAT runs were acquired together, from their DICOM headers (start times, single-plane
    runs' frames of reference). Sequential runs (a monoplane C-arm: two injections minutes apart) get a pose per
    run and the motion between them; their verdict is never `ok` (motion along each beam cannot be measured)."""

    model_config = CLOSED

    sequential: bool = Field(description="True: two runs at different times, the head may have moved between them.")
    basis: str = Field(description="What says so, in words (the runs' start times, or their frames of reference).")
    interval_s: float | None = Field(None, description="LAT run start − AP run start, seconds; null without both times.")
    run_poses: dict[str, Matrix4] | None = Field(
        None, description="Sequential runs: per view (`ap`, `lat`), 4x4 mesh mm → world mm of the model at that run: "
                          "the joint pose refined on that view alone, its depth along the view's beam held at the "
                          "joint pose's (one view cannot measure it).")
    run_dice: dict[str, float] | None = Field(None, description="Per view: Dice (0–1) of the silhouette at that "
                                                                "run's pose with the vessel mask.")
    motion: Motion | None = Field(None, description="Sequential runs: the model's motion from the AP run to the LAT "
                                                    "run (across the beams; along them it is not measured).")
    seconds: float | None = Field(None, description="Time spent on the per-run poses, seconds.")
