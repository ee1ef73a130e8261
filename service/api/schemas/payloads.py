"""Typed payloads of the OpenAPI document: geometry, options, result (and the multipart parts).

These models declare the payloads with descriptions, units, examples and enums, and
:func:`document` puts them into ``/openapi.json``:

* ``components.schemas``: ``RegistrationOptions``, ``ViewSpec`` and ``LatFromAp`` (the engine's own
  models, so the fields cannot drift), ``GeometryFile`` (the engine's ``RigSpec``, its view names spelled
  out), ``RegistrationResult`` /
  ``ViewResult`` / ``ResultMetrics`` / ``GroundTruthErrors``;
* the ``POST /v1/registrations`` multipart parts, each with its schema and encoding;
* ``JobStatus.result`` and ``GET …/result`` point at ``RegistrationResult``.

The result contract is closed: every model here refuses undeclared fields (``CLOSED``, published as
``additionalProperties: false``), so every field the engine writes into ``result.json`` must be
declared here, with a description (docs/api/result-contract.md); the tests validate every result they
produce against :class:`RegistrationResult` (tests/support/result_contract.py).
"""

from __future__ import annotations

from enum import Enum
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field

from ...engine_adapter import engine
from .closed import CLOSED
from .dimse_result import DimseExport, DimseSourceInfo
from .hemodynamics import HemodynamicsSummary

Matrix4 = list[list[float]]
Matrix34 = list[list[float]]
IDENTITY = [[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0], [0.0, 0.0, 0.0, 1.0]]
REF = "#/components/schemas/{model}"


# ---- geometry file ---------------------------------------------------------------------------


class GeometryFile(engine.RigSpec):
    """The C-arm geometry (the `geometry` part): two views in world millimetres and the initial pose.
    Instead of JSON, the part may be a preset name (`paper`), or be left out when both images are
    DICOM XA (or `.rad`) files whose headers carry the geometry."""

    model_config = ConfigDict(CLOSED, json_schema_extra={"examples": [{
        "views": {"ap": {"image_size": [800, 800], "pixel_spacing_mm": [0.3, 0.3], "sid_mm": 1200.0,
                         "world_to_view": [[0, 0, -1, 0], [0, 1, 0, 0], [1, 0, 0, 750], [0, 0, 0, 1]]}},
        "lat_from_ap": {"angle_deg": 90.0}, "initial_mesh_to_world": IDENTITY}]})

    views: dict[Literal["ap", "lat"], engine.ViewSpec] = Field(description="The views by name: `ap` and `lat`.")


# ---- result ---------------------------------------------------------------------------------


class GroundTruthErrors(BaseModel):
    """Errors against `options.ground_truth_mesh_to_world` (synthetic studies)."""

    model_config = CLOSED

    rotation_error_deg: float | None = Field(None, description="Angle of the rotation difference, degrees.")
    translation_error_mm: float | None = Field(
        None, description="Distance of the AP source position in the mesh frame, mm (the paper's definition).")
    add_mm: float | None = Field(None, description="Average distance of the mesh vertices, mm.")
    mtre_mm: float | None = Field(None, description="Mean target registration error, mm.")
    mpd_mm: dict[str, float | None] | None = Field(None, description="Mean projection distance per view, mm.")
    initial_mtre_mm: float | None = Field(None, description="mTRE of the initial pose, mm.")


class Verdict(str, Enum):
    """Whether to trust the pose: `ok` use it, `check` look at the overlays first, `failed` do not use it."""

    ok = "ok"
    check = "check"
    failed = "failed"


class RunnerUp(BaseModel):
    """The best start that ended at a distinct pose, and how well it and the kept pose fit."""

    model_config = CLOSED

    distance_mm: float = Field(description="Mean vertex distance of that pose from the kept one, mm.")
    best_fit: float = Field(description="Fit of the kept pose (tolerant F-score, 0–1, mean over the views).")
    fit: float = Field(description="Fit of the distinct pose (same measure); close to best_fit = ambiguous.")


class PartRunnerUp(BaseModel):
    """Another part of the model that matched the filled vessels almost as well as the one the fit started from."""

    model_config = CLOSED

    score: float = Field(description="Its coverage score, 1 − F1 (0 best, 1 worst).")
    distance_mm: float = Field(description="Mean vertex distance of the whole model at its pose from the leading part's, mm.")


class MirrorCheck(BaseModel):
    """The mirror check (`dsareg_engine.registration.mirror`): run only when some view's Dice was below 0.7."""

    model_config = CLOSED
    dice: dict[str, float] = Field(description="Per view: Dice (0–1) of the model's mirror image, registered from a "
                                               "search of rotations.")
    mirrored: bool = Field(description="True when the mirror fits clearly better (lowest Dice ≥ 0.7 and ≥ 0.2 above "
                                       "the model's): the verdict is then `failed`, the model seems mirrored.")
    axis: Literal["x", "y", "z"] | None = Field(
        None, description="The model axis that seems flipped, judged against the initial pose given; null without "
                          "one (a mirror along any axis is the same up to a rotation).")


class ConfidenceSignals(BaseModel):
    """The measurements the verdict is made of (see docs/api/results.md)."""

    model_config = CLOSED

    dice: dict[str, float] = Field(
        default_factory=dict, description="Per view: Dice (0–1) of the registered silhouette with the vessel mask "
                                          "as fitted (its border moved by the border correction).")
    runner_up: RunnerUp | None = Field(None, description="A distinct pose that fits almost as well, or null.")
    border_shift_px: dict[str, float] | None = Field(
        None, description="Per view: how far the border correction moved the mask outline, pixels (signed).")
    outside_fraction: dict[str, float] = Field(
        default_factory=dict, description="Per view: fraction (0–1) of the model's vertices projecting outside the image.")
    stopped_on_tolerance: bool | None = Field(
        None, description="True when the final stage stopped because the pose stopped changing (not the iteration cap).")
    unmatched_fraction: dict[str, float] | None = Field(
        None, description="Per view: fraction (0–1) of the model's registered silhouette farther than 2 px from any "
                          "vessel of the mask (model branches the run did not fill, or a wrong pose).")
    uncovered_fraction: dict[str, float] | None = Field(
        None, description="Per view: fraction (0–1) of the vessel mask farther than 2 px from the model's silhouette "
                          "(vessels the model lacks, or a wrong pose).")
    partial_loss: bool | None = Field(
        None, description="True when the fit used the loss for partial visibility (background farther than 2 px "
                          "from the vessels weighed 0.05), because the images show only part of the model.")
    part_runner_up: PartRunnerUp | None = Field(
        None, description="When one part of the model led the fit alone (the branch search): another part scoring "
                          "almost as well (within 0.02) at a distinct pose, or null; the partial reason then says the "
                          "pose is uncertain.")
    mirror: MirrorCheck | None = Field(None, description="The model's mirror image fitted too, because the fit was "
                                                          "poor; absent when it was not needed.")


class Confidence(BaseModel):
    """The verdict on the pose and why. `check` with the partial-visibility reason ("the model has vessels the
    images do not show"): every view has `unmatched_fraction` ≥ 0.1 and `uncovered_fraction` ≤ 0.05, consistently
    across views (the Dice rules are then skipped). Otherwise `failed`: some view's Dice < 0.5; `check`: any
    view's Dice < 0.7, a distinct pose fits almost as well, a border shift ≥ 1.5 px, > 25 % of the model outside
    an image, or the iteration cap was hit; else `ok`."""

    model_config = ConfigDict(CLOSED, json_schema_extra={"examples": [{
        "verdict": "failed", "reasons": ["ap: the model's silhouette overlaps the vessels poorly (dice 0.25)"],
        "signals": {"dice": {"ap": 0.25, "lat": 0.31}, "runner_up": None, "border_shift_px": {"ap": 0.1, "lat": 0.0},
                    "outside_fraction": {"ap": 0.0, "lat": 0.0}, "stopped_on_tolerance": True,
                    "unmatched_fraction": {"ap": 0.61, "lat": 0.58}, "uncovered_fraction": {"ap": 0.47, "lat": 0.52},
                    "partial_loss": False}}]})

    verdict: Verdict = Field(description="ok: use the pose; check: look at the overlays first; failed: do not use it.")
    reasons: list[str] = Field(default_factory=list,
                               description="Plain-word sentences, one per finding (empty when ok); failed ones first.")
    signals: ConfidenceSignals = Field(default_factory=ConfidenceSignals)


class CoverageSearch(BaseModel):
    """Best candidate of the coverage search (partial visibility): how much of the vessels the whole model explains."""

    model_config = CLOSED

    best_score: float = Field(description="1 − F₂ of precision and recall, mean over the views (0 best, 1 worst).")
    precision: list[float] = Field(description="Per view (AP, LAT order): share (0–1) of the model's points on or next to vessels.")
    recall: list[float] = Field(description="Per view: share (0–1) of the vessel pixels the model reaches.")


class WholeModelCoverage(BaseModel):
    """The whole-model search's starts placed by coverage: does one lie on the vessels (else the partial searches run)?"""

    model_config = CLOSED

    model_explained: bool = Field(description="True when, in every view, ≥ 90 % of the start's model pixels lie on or "
                                              "next to vessels: the images show the whole model, and the coverage and "
                                              "branch searches are skipped.")
    best_score: float = Field(description="That start's 1 − F₂ of precision and recall, mean over the views (0 best, 1 worst).")
    precision: list[float] = Field(description="Per view (AP, LAT order): share (0–1) of the start's model points on or next to vessels.")
    recall: list[float] = Field(description="Per view: share (0–1) of the vessel pixels the start reaches.")
    images_hold_more: bool | None = Field(None, description="True when some start lies on the vessels but none of those "
                                          "reaches 70 % of them in every view: the images hold more than the model "
                                          "(another territory, small branches, background), and the precision-weighted "
                                          "coverage search's candidates lead the starts (method search+precise).")


class BranchSearch(BaseModel):
    """Best part of the branch search (partial visibility): the model cut to one branch and what lies downstream."""

    model_config = CLOSED

    parts_searched: int = Field(description="Parts of the model (branches) searched, count.")
    best_score: float | None = Field(None, description="The best part's coverage score, 1 − F1 (0 best, 1 worst).")
    whole_score: float | None = Field(None, description="The whole model's coverage score by the same search (0 best, 1 worst).")
    faces_fraction: float | None = Field(None, description="The best part's share (0–1) of the model's faces.")
    proximal: bool | None = Field(None, description="True when the best part is a proximal one (the faces nearest the "
                                  "inflow, as an early arterial frame fills them): the whole model is then fitted from its pose.")
    runner_up: PartRunnerUp | None = Field(None, description="When one part led alone: another part scoring almost as "
                                                             "well at a distinct pose, or null.")
    matches: bool | None = Field(None, description="True when some part or the whole model scored below 0.2 (it matches "
                                 "the images as a visible model does); false: nothing of the model is on the images "
                                 "(another tree, swapped views) and the fit ran from the first start alone.")


class Initialization(BaseModel):
    """Where the optimization started: a given pose, or a search over candidate poses."""

    model_config = CLOSED

    method: Literal["given", "search", "search+coverage", "search+branch", "search+coverage+branch", "search+precise"] = Field(
        description="given: the geometry's / options' initial pose; search: the best candidates of a pose search; "
                    "+coverage / +branch: the images looked partial and the coverage search's / the branch search's "
                    "candidates lead the starts; +precise: the images held more than the model and the "
                    "precision-weighted coverage search's candidates lead (docs/concepts/verdict.md).")
    candidates_scored: int = Field(0, description="Rotations scored by the whole-model searches (0 when given).")
    seconds: float = Field(0.0, description="Time of the search, seconds.")
    best_score: float | None = Field(None, description="Search score of the best start (0 best, 1 worst).")
    runner_up_score: float | None = Field(None, description="Score of the second-best start.")
    coverage: CoverageSearch | None = Field(None, description="The coverage search's best candidate (null when it did "
                                                              "not run: a whole-model start lay on the vessels).")
    explained: WholeModelCoverage | None = Field(None, description="Whether a whole-model start lies on the vessels, "
                                                                   "all of it (null when the pose was given).")
    branch: BranchSearch | None = Field(None, description="The branch search's best part (null when it did not run).")


class Motion(BaseModel):
    """Motion since the previous pose (tracking jobs: `POST …/track`, `options.mode: "track"`)."""

    model_config = CLOSED

    rotation_deg: float = Field(description="Angle of the relative rotation, degrees.")
    translation_mm: float = Field(description="Displacement of the model's centroid, world mm.")
    mean_displacement_mm: float = Field(description="Mean displacement of the model's vertices, mm.")
    world_motion: Matrix4 | None = Field(None, description="4x4 current · previous⁻¹ (world frame).")
    rotation_vector_deg: list[float] | None = Field(
        None, min_length=3, max_length=3, description="The rotation's axis times its angle, degrees, world frame "
                                                      "(its norm is rotation_deg).")
    translation_vector_mm: list[float] | None = Field(
        None, min_length=3, max_length=3, description="Displacement of the model's centroid, world mm (its norm is "
                                                      "translation_mm).")


class Tracking(BaseModel):
    """A tracking job over a procedure (`POST …/track`, `options.mode: "track"`): the planes fitted, the motion since
    the procedure's first pose and since the previous one, and what one plane cannot measure (docs/api/results.md)."""

    model_config = CLOSED

    views: list[Literal["ap", "lat"]] = Field(description="The planes fitted this time: one (a single-plane run) or both.")
    frame: Literal["world"] = Field(description="The frame of every vector here: the geometry's world frame (DICOM XA: "
                                                "patient LPS axes, origin at the isocentre), mm.")
    reference_mesh_to_world: Matrix4 = Field(description="4x4 mesh mm → world mm: the procedure's first pose (the "
                                                         "first job's result), or the previous pose when none was given.")
    reference_given: bool = Field(description="False: no reference was given (options.reference_mesh_to_world), the "
                                              "previous pose stands for it.")
    since_reference: Motion = Field(description="The model's motion from the reference pose to this one.")
    since_previous: Motion = Field(description="The model's motion from the previous pose to this one (= "
                                               "metrics.motion).")
    along_beam_measured: bool = Field(description="False for one plane: one view shows the motion along its beam "
                                                  "through perspective alone (confounded with the model's scale); the "
                                                  "verdict is then at most `check` with the reason.")
    unmeasured_view: Literal["ap", "lat"] | None = Field(None, description="One plane: the plane whose beam direction "
                                                                          "was not measured.")
    unmeasured_direction_world: list[float] | None = Field(
        None, min_length=3, max_length=3, description="One plane: unit vector (world) from its X-ray source through the "
                                                      "model's centroid, along which the motion was not measured.")
    along_beam_mm: float | None = Field(None, description="One plane: the motion since the previous pose along that "
                                                          "direction (signed, mm; near 0 with depth `previous`): the part "
                                                          "not measured.")
    depth: Literal["fit", "previous"] | None = Field(None, description="One plane: where the depth along its beam "
                                                                       "comes from (options.single_plane_depth): the "
                                                                       "fit's perspective, or held at the previous pose's.")
    depth_held_mm: float | None = Field(None, description="One plane, depth `previous`: how far the fitted pose was "
                                                          "moved back along the beam to the previous pose's depth, mm.")


class ResultMetrics(BaseModel):
    """How the registration went."""

    model_config = ConfigDict(CLOSED, json_schema_extra={"examples": [{
        "loss": 0.0019, "iterations": {"ap+lat:1/4": 17, "ap+lat:1/2": 27, "ap+lat:1/1": 37, "ap+lat:1/1:refine": 11},
        "seconds": {"ap+lat:1/4": 0.72, "ap+lat:1/2": 0.64, "ap+lat:1/1": 1.68, "ap+lat:1/1:refine": 0.41,
                    "total": 5.5},
        "device": "cpu", "converged": True, "reason": "pose change below tolerance in the final stage",
        "starts": 4, "starts_agreeing": 4, "configuration": "simultaneous",
        "border_shift_px": {"ap": -0.008, "lat": 0.004}}]})

    loss: float | None = Field(None, description="Final loss (mean squared silhouette error), dimensionless.")
    iterations: dict[str, int] = Field(default_factory=dict, description="Iterations per stage, in the order run.")
    seconds: dict[str, float] = Field(default_factory=dict, description="Seconds per stage and `total`.")
    device: str | None = Field(None, description="Where it ran (`cpu`, `cuda`).")
    converged: bool | None = Field(
        None, description="True only when the final stage stopped on the pose-change rule and every view's Dice ≥ 0.5.")
    reason: str | None = Field(None, description="Why converged is what it is.")
    starts: int | None = Field(None, description="Initial poses tried.")
    starts_agreeing: int | None = Field(None, description=(
        "Starts within 2 mm ADD of the best where the starts were last compared (the coarse levels, where "
        "agreeing starts still differ by 1-3 mm): a lower bound."))
    configuration: Literal["ap", "lat", "simultaneous", "ap_then_lat", "lat_then_ap"] | None = None
    border_shift_px: dict[str, float] | None = Field(
        None, description="Measured mask border offset per view, pixels (border correction).")
    warnings: list[str] | None = Field(None, description="Notes on the result (e.g. single-view ambiguity).")
    ground_truth: GroundTruthErrors | None = None
    confidence: Confidence | None = Field(None, description="The verdict on the pose and its reasons (every result "
                                                            "of this version has one).")
    initialization: Initialization | None = None
    mode: Literal["register", "track"] | None = Field(None, description="track: a tracking job (then `motion`).")
    motion: Motion | None = None
    tracking: Tracking | None = Field(None, description="Tracking jobs: the planes fitted, the motion since the "
                                                        "procedure's first pose and since the previous one, what one "
                                                        "plane cannot measure.")


class DetectorGeometry(BaseModel):
    """The C-arm of one view as it stood, world mm (the rig's convention: source at the view frame's origin, the
    image plane at z = sid_mm)."""

    model_config = ConfigDict(extra="forbid")

    source_mm: list[float] = Field(min_length=3, max_length=3, description="X-ray source position, world mm.")
    corners_mm: list[list[float]] = Field(min_length=4, max_length=4, description=(
        "World mm of the image's outer corners on the detector: top-left, top-right, bottom-right, bottom-left of "
        "the stored image (pixel edges, (u, v) = (-0.5, -0.5) … (W-0.5, H-0.5))."))
    image_size_px: list[int] = Field(min_length=2, max_length=2, description="(W, H) of the image registered.")
    sid_mm: float = Field(description="Source-to-detector distance, mm.")
    pixel_spacing_mm: list[float] = Field(min_length=2, max_length=2, description="(du, dv) at the detector, mm.")
    mm_per_px_at_model: float | None = Field(None, description="A pixel's size at the depth of the model's centre "
                                                               "(registered pose), mm: one mm scale for both views.")


class ViewResult(BaseModel):
    """Per-view outcome."""

    model_config = CLOSED

    world_to_view: Matrix4 = Field(description="4x4 world mm → view frame (the geometry's, unchanged).")
    mesh_to_view: Matrix4 = Field(description="4x4 = world_to_view · mesh_to_world.")
    projection_matrix: Matrix34 = Field(description="3x4 homogeneous mesh-frame mm → homogeneous pixels.")
    dice: float = Field(ge=0, le=1, description="Dice of the registered hard silhouette with the vessel mask.")
    iou: float = Field(ge=0, le=1, description="Intersection over union of the same.")
    detector: DetectorGeometry | None = Field(None, description="Where the source and the detector stood "
                                                                "(the review page's 3D scene; model.json repeats it).")
    image_from_job: str | None = Field(
        None, description="A tracking job sent one plane only (POST …/track): this view's image is not from this job's "
                          "run but an earlier one's, carried along: the id of the job it was sent with. The view was "
                          "not fitted (metrics.tracking.views); its overlay and Dice show the new pose on that earlier "
                          "image. Null: the image came with this job.")


class DicomInstance(BaseModel):
    """One DICOM object the job wrote (`GET …/dicom/{name}`)."""

    model_config = CLOSED

    sop_class_uid: str
    sop_instance_uid: str
    series_instance_uid: str | None = None
    study_instance_uid: str | None = None


class DicomSource(BaseModel):
    """Where the inputs of a job by reference came from."""

    model_config = CLOSED

    server: str | None = Field(None, description="The DICOMweb base URL.")
    study_uid: str | None = None
    fetch_seconds: float | None = Field(None, description="Time to fetch the inputs, seconds.")
    requests: int | None = Field(None, description="HTTP requests made to fetch them.")
    dimse: DimseSourceInfo | None = Field(None, description="Inputs that came over DIMSE: a received study, or a pull.")


class DicomStored(BaseModel):
    """What was stored back into the PACS (STOW-RS) for a job by reference with `store_results`."""

    model_config = CLOSED

    server: str | None = None
    study_uid: str | None = None
    sop_instance_uids: list[str] = Field(default_factory=list)
    confirmed: bool | None = Field(None, description="True when the PACS confirmed every instance.")
    store_seconds: float | None = None


class DicomResult(BaseModel):
    """The DICOM results: REG (model → C-arm frame) and Secondary Captures."""

    model_config = CLOSED

    instances: dict[str, DicomInstance] = Field(
        default_factory=dict, description="By file name (`reg.dcm`, `overlay_ap.dcm`, `overlay_lat.dcm`, `loss.dcm`; "
                                          "with options.hemodynamics `parametric_ap.dcm`, `parametric_lat.dcm`).")
    source: DicomSource | None = None
    stored: DicomStored | None = Field(None, description="Jobs made before the exports left the worker only: their "
                                                         "STOW-RS (now the job's `export`).")
    exported: list[DimseExport] | None = Field(None, description="Jobs made before the exports left the worker only: "
                                                                 "their C-STORE to each destination (now the job's "
                                                                 "`export`).")


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


class RegistrationResult(BaseModel):
    """The registration result (`result.json`). `verdict` says whether to trust `mesh_to_world`; a job that
    `succeeded` only ran to the end. Every field is declared (none undeclared is written); a later version may
    declare more, so clients should ignore fields they do not know."""

    model_config = ConfigDict(CLOSED, json_schema_extra={"examples": [{
        "mesh_to_world": IDENTITY, "initial_mesh_to_world": IDENTITY, "verdict": "ok",
        "views": {"ap": {"world_to_view": IDENTITY, "mesh_to_view": IDENTITY,
                         "projection_matrix": [[692.8, 0, 399.5, 0], [0, 692.8, 399.5, 0], [0, 0, 1, 0]],
                         "dice": 0.997, "iou": 0.994}},
        "metrics": {"loss": 0.0019, "converged": True, "reason": "pose change below tolerance in the final stage",
                    "confidence": {"verdict": "ok", "reasons": [], "signals": {}}}}]})

    mesh_to_world: Matrix4 = Field(description="4x4 rigid estimated pose, mesh mm → world mm: the answer.")
    initial_mesh_to_world: Matrix4 | None = Field(None, description="4x4 pose the registration started from.")
    views: dict[str, ViewResult] = Field(description="Per view (`ap`, `lat`).")
    metrics: ResultMetrics
    warnings: list[str] | None = Field(None, description="Notes from reading the inputs (decimation, resizing...).")
    image_reading: dict[str, ImageReadingRecord] | None = Field(
        None, description="Per view, what was read from a multi-frame XA run (frames, mask frames, recipe, shift).")
    verdict: Verdict | None = Field(
        None, description="= metrics.confidence.verdict: ok (use the pose), check (look at the overlays first), "
                          "failed (do not use it). Null only for results of versions before the verdict.")
    dicom: DicomResult | None = Field(None, description="The DICOM objects written (and fetched/stored in a PACS).")
    volume: VolumeRead | None = Field(None, description="For a volume input: what was read from it.")
    input_decisions: list[InputDecisionRecord] | None = Field(
        None, description="The decisions taken about the inputs (run kind, mask frames, frames combined, volume kind "
                          "and window, units, handedness), each with its measure and margin.")
    hemodynamics: HemodynamicsSummary | None = Field(
        None, description="With options.hemodynamics: contrast arrival and time to peak on the model from both runs "
                          "(per-vertex values: links.hemodynamics).")
    acquisition: Acquisition | None = Field(
        None, description="DICOM XA runs: whether they were acquired together; sequential runs add a pose per run and "
                          "the motion between them (null without DICOM headers saying either).")


# ---- putting them into the OpenAPI document -----------------------------------------------


def _components(*models: type[BaseModel]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for model in models:
        schema = model.model_json_schema(ref_template=REF, mode="serialization")
        out.update(schema.pop("$defs", {}))
        out[model.__name__] = schema
    return out


def options_model() -> type[BaseModel]:
    from ...engine_adapter import engine

    return engine.RegistrationOptions


def multipart_schema(presets: list[str]) -> dict[str, Any]:
    """The multipart/form-data body of ``POST /v1/registrations``."""
    return {
        "type": "object",
        "required": ["ap", "lat"],
        "description": "Give `mesh` or `volume`, both images, and optionally `geometry` and `options`.",
        "properties": {
            "mesh": {"type": "string", "format": "binary",
                     "description": "Vessel surface mesh in mm: OBJ, STL (ASCII/binary), PLY, OFF, GLB, VTP or legacy "
                                    "VTK polydata."},
            "volume": {"type": "array", "items": {"type": "string", "format": "binary"},
                       "description": "Vessel volume instead of a mesh: NIfTI, NRRD (`.nhdr` + its data file as two "
                                      "parts), MetaImage (`.mha`, or `.mhd` + its data file), legacy VTK structured "
                                      "points, a DICOM series (one part per file) or `.rad` + `.raw`; its vessels read "
                                      "by kind (CTA, TOF-MRA, 3D-DSA) or as a label map, and meshed (marching cubes)."},
            "ap": {"type": "string", "format": "binary",
                   "description": "AP view: DSA image or binary vessel mask (PNG, TIFF, JPEG, DICOM XA single/"
                                  "multi-frame); a `.rad` + `.raw` pair as two parts."},
            "lat": {"type": "string", "format": "binary", "description": "LAT view, as `ap`."},
            "geometry": {
                "description": "The C-arm geometry: a preset name, GeometryFile JSON (text or a file part), or "
                               "nothing when DICOM XA / .rad headers carry it.",
                "anyOf": [
                    {"type": "string", "enum": presets, "description": "A preset name."},
                    {"type": "string", "contentMediaType": "application/json",
                     "contentSchema": {"$ref": REF.format(model="GeometryFile")}},
                ],
                "examples": [presets[0] if presets else "paper"],
            },
            "options": {
                "type": "string", "contentMediaType": "application/json",
                "contentSchema": {"$ref": REF.format(model="RegistrationOptions")},
                "description": "RegistrationOptions as JSON text; every field is optional.",
                "examples": ['{"starts": 2, "max_iterations": 300}'],
            },
            "callback_url": {
                "type": "string", "maxLength": 2048,
                "description": "POSTed the job summary (JobSummary JSON, signed) once the job ends; must start with "
                               "one of the server's DSAREG_CALLBACK_ALLOWED prefixes, else 422.",
                "examples": ["https://ris.example.org/dsareg-hooks/job-done"],
            },
        },
    }


def reference_model() -> type[BaseModel]:
    from ...pacs.dicomweb import DicomwebRegistrationRequest

    return DicomwebRegistrationRequest


def dimse_reference_model() -> type[BaseModel]:
    from ...pacs.dimse.pull import DimseRegistrationRequest

    return DimseRegistrationRequest


def json_body_schema() -> dict[str, Any]:
    """The ``application/json`` body: inputs by DICOMweb or by DIMSE reference, told apart by the key of ``source``."""
    return {"oneOf": [{"$ref": REF.format(model=reference_model().__name__)},
                      {"$ref": REF.format(model=dimse_reference_model().__name__)}],
            "description": 'Inputs by reference: `{"source": {"dicomweb": ...}}` (QIDO/WADO-RS) or '
                           '`{"source": {"dimse": ...}}` (C-MOVE / C-GET from a DSAREG_DICOM_PEERS peer); '
                           "the single key of `source` says which."}


def document(schema: dict[str, Any]) -> dict[str, Any]:
    """Add the payload schemas to an OpenAPI document (in place; returned for convenience)."""
    from ...engine_adapter import engine

    PRESETS = engine.PRESETS

    schemas = schema.setdefault("components", {}).setdefault("schemas", {})
    schemas.update(_components(options_model(), GeometryFile, RegistrationResult, reference_model(),
                               dimse_reference_model()))
    result_ref = {"$ref": REF.format(model="RegistrationResult")}
    for name in ("JobStatus", "JobStatus-Output"):
        props = schemas.get(name, {}).get("properties", {})
        if "result" in props:
            props["result"] = {"anyOf": [result_ref, {"type": "null"}],
                               "description": "The registration result when succeeded, else null."}
    paths = schema.get("paths", {})
    post = paths.get("/v1/registrations", {}).get("post")
    if post is not None:
        post["requestBody"] = {"required": True, "content": {
            "multipart/form-data": {
                "schema": multipart_schema(sorted(PRESETS)),
                "encoding": {"options": {"contentType": "application/json, text/plain"},
                             "geometry": {"contentType": "text/plain, application/json"},
                             "volume": {"contentType": "application/octet-stream"}},
            },
            # inputs by DICOMweb or DIMSE reference (service/intake/reference.py)
            "application/json": {"schema": json_body_schema()},
        }}
    get_result = paths.get("/v1/registrations/{job_id}/result", {}).get("get")
    if get_result is not None:
        ok = get_result.setdefault("responses", {}).setdefault("200", {})
        ok["description"] = "The registration result."
        ok["content"] = {"application/json": {"schema": result_ref}}
    return schema
