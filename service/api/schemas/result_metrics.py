"""The result's metrics: errors against a ground truth, how the pose was found (searches, initialization),
the motion between runs, tracking, and ``ResultMetrics`` that holds them."""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field

from .closed import CLOSED
from .confidence import Confidence, PartRunnerUp

Matrix4 = list[list[float]]


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
