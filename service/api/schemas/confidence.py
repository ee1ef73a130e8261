"""The result's verdict and what it rests on: the confidence signals, runners-up, the mirror check."""

from __future__ import annotations

from enum import Enum
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field

from .closed import CLOSED


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
    final_step_mm: float | None = Field(
        None, description="When the iteration cap stopped the final stage: the largest of its last three Gauss–Newton "
                          "steps, mm (how far the fit's own model still puts the optimum); below 0.01 the pose has "
                          "settled and the cap is no reason to check. Null otherwise.")
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
    an image, or the iteration cap was hit before the pose settled (`final_step_mm` null or ≥ 0.01); else `ok`."""

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
