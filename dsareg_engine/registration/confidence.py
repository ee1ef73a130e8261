"""How sure is a registration? A plain verdict (``ok`` / ``check`` / ``failed``) with reasons.

Signals, all measured by the solver (``metrics.confidence.signals``):

* ``dice``: final hard silhouette vs the mask per view, the mask's border moved by the border
  correction (the target actually fitted; a uniformly too wide mask is the border signal's
  business, not a wrong pose). Low overlap means a wrong pose (or a mask of something else).
* ``runner_up``: the best start that ended *elsewhere* (mean vertex distance from the kept
  pose > 20 % of the mesh's RMS radius and > 2 mm) when the batched stages hand over, with
  its fit and the kept start's (mean over the views of :func:`tolerant_f_score`, full-resolution hard silhouettes, 3 px
  tolerance: the poses are not refined yet). A distinct pose explaining the images
  almost as well (small gap) is an ambiguity the images cannot settle (a symmetric
  vessel, a foreshortened view). Loss ratios were tried first and do not separate: at the
  hand-over level the soft silhouettes leave a loss floor, so wrong minima read only 1.3–2×.
* ``border_shift_px``: how far the border correction had to move each mask's outline; near
  its clamp the mask's width does not match the model (wrong segmentation threshold,
  different vessel calibre, a scaled mesh).
* ``outside_fraction``: fraction of the model's vertices projecting outside each image;
  what is outside is unconstrained.
* ``reason``: the optimizer's stop (iteration limit = did not settle).
* ``unmatched_fraction`` / ``uncovered_fraction`` per view: the share of the model's silhouette
  farther than 2 px from any vessel, and of the vessels farther than 2 px from the silhouette
  (:mod:`.partial`). Together they tell the three ways a fit can fall short apart: part of the
  model unmatched in *every* view while the vessels are all explained, consistently across the
  views, is a model holding vessels the run did not fill (partial visibility: ``check``, the pose
  is usable); vessels left uncovered while the model is all matched is the run showing vessels the
  model lacks (``check``: a model of one territory or without its small branches, background in the
  segmentation — or the model slid onto vessels that are not its own); both at once is a wrong pose.
  ``partial_loss``: the fit used the trimmed loss.
* ``part_runner_up``: when one part of the model led the fit alone (:mod:`.branch_search`), another part
  that scored almost as well at a distinct pose (``{"score", "distance_mm"}``), or None; the partial
  reason then says the pose is uncertain instead of "the pose fits the filled vessels".

Thresholds (:class:`ConfidenceThresholds`) were calibrated on the robustness studies; see the
README's calibration table.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..geometry.rig import ViewGeometry
from ..metrics import mean_distance_mm, within_px


@dataclass(frozen=True)
class ConfidenceThresholds:
    """Where a signal turns the verdict (see the README's calibration table).

    Attributes:
        failed_dice: below this Dice in any view the pose is wrong.
        check_dice: below this Dice in any view the pose needs a look.
        ambiguous_fit_gap: a distinct solution whose fit (tolerant F-score) is within this of the kept one's.
        border_shift_px: |border shift| at or above this (the correction's clamp is 2 px).
        outside_fraction: more of the model than this projects outside an image.
    """

    failed_dice: float = 0.5
    check_dice: float = 0.7
    settled_step_mm: float = 0.01
    """A final stage stopped by its iteration cap has settled when its last Gauss–Newton steps (the fit's own
    estimate of how far the optimum still is) each moved the model less than this (a tenth of the 0.1-mm target):
    at 512 px a CTA model's fit creeps by 1.5–4 µm a step, its loss by 10⁻⁴ a step, and never meets the 10⁻⁴-mm
    step rule."""
    ambiguous_fit_gap: float = 0.05
    fit_tolerance_px: float = 3.0
    border_shift_px: float = 1.5
    outside_fraction: float = 0.25
    partial_unmatched: float = 0.1
    """Partial visibility: at least this share of the silhouette unmatched in every view ..."""
    partial_uncovered: float = 0.05
    """... at most this share of the vessels uncovered in every view ..."""
    partial_consistency: float = 0.25
    """... and the views' unmatched shares within this of each other."""
    missing_uncovered: float = 0.1
    """A low overlap's wording: the images show vessels the model lacks when at least this share is uncovered in a
    view whose silhouette is matched."""
    more_uncovered: float = 0.25
    """The verdict's check for images holding more than the model: at least this share uncovered in every view whose
    silhouette is matched. Not less: a CTA model without the small branches the DSA shows leaves 15-20 % of the
    vessels off the model at the right pose (the whole-head CTA: 15 % / 17 %, ADD 0.095 mm), the usual case rather
    than a doubt; from 25 %, a territory or background the pose could have been drawn to."""


def runner_up(poses: np.ndarray, losses: np.ndarray, points: np.ndarray, distinct_mm: float) -> tuple[int, float] | None:
    """Index of the best of ``poses`` ``(B, 4, 4)`` (by ``losses`` ``(B,)``) farther than ``distinct_mm``
    (mean ``points`` distance) from the best one, and that distance; None when every start agrees."""
    order = np.argsort(losses)
    for index in order[1:]:
        distance = mean_distance_mm(poses[index], poses[order[0]], points)
        if distance > distinct_mm:
            return int(index), distance
    return None


def tolerant_f_score(silhouette: np.ndarray, mask: np.ndarray, tolerance_px: float) -> float:
    """F-score of two ``(H, W)`` bool masks counting pixels within ``tolerance_px`` of the other as matched.

    Unlike Dice it forgives the pixel-level misfit of a pose not yet refined, so a coarse
    pose near the right answer reads near 1 and a wrong local minimum does not.
    """
    if not silhouette.any() or not mask.any():
        return 0.0
    precision = float((silhouette & within_px(mask, tolerance_px)).sum() / silhouette.sum())
    recall = float((mask & within_px(silhouette, tolerance_px)).sum() / mask.sum())
    return 0.0 if precision + recall == 0 else 2.0 * precision * recall / (precision + recall)


def outside_fraction(view: ViewGeometry, points_world: np.ndarray) -> float:
    """Fraction of ``points_world`` ``(N, 3)`` projecting outside the view's image."""
    pixels = view.project(points_world)
    inside = np.all((pixels >= -0.5) & (pixels <= np.array(view.image_size) - 0.5), axis=1)
    return float(1.0 - inside.mean())


def assess(signals: dict, thresholds: ConfidenceThresholds = ConfidenceThresholds()) -> dict:
    """``{"verdict", "reasons", "signals"}`` from ``signals`` = {dice: {view: float},
    runner_up: dict | None, border_shift_px: {view: float}, outside_fraction: {view: float},
    stopped_on_tolerance: bool, final_step_mm: float | None (a capped final stage's last steps)}."""
    failed, check = [], []
    partial = _partial_visibility(signals, thresholds)
    if partial is not None:
        check.append(partial)
    more = None if partial is not None else _images_hold_more(signals, thresholds)
    if more is not None:
        check.append(more)
    for name, value in signals["dice"].items():
        if partial is not None:
            break  # the low overlap is the unfilled model's, explained above
        if value < thresholds.failed_dice:
            failed.append(f"{name}: the model's silhouette overlaps the vessels poorly (fitted dice {value:.2f}); "
                          f"{_why_low(signals, name, thresholds)}")
        elif value < thresholds.check_dice:
            check.append(f"{name}: partial overlap (fitted dice {value:.2f}); {_why_low(signals, name, thresholds)}")
    other = signals.get("runner_up")
    if other is not None and other["best_fit"] - other["fit"] < thresholds.ambiguous_fit_gap:
        check.append(f"ambiguous: a different pose {other['distance_mm']:.0f} mm away fits almost as well "
                     f"({other['fit']:.2f} vs {other['best_fit']:.2f}); a symmetric or foreshortened vessel?")
    for name, shift in (signals.get("border_shift_px") or {}).items():
        if abs(shift) >= thresholds.border_shift_px:
            check.append(f"{name}: vessel borders had to move {shift:+.1f} px to match the model "
                         "(segmentation width or mesh scale differ)")
    for name, fraction in signals["outside_fraction"].items():
        if fraction > thresholds.outside_fraction:
            check.append(f"{name}: {fraction:.0%} of the model projects outside the image and is unconstrained")
    if not signals.get("stopped_on_tolerance", True) and not settled(signals.get("final_step_mm"), thresholds):
        check.append("the optimizer hit its iteration limit before the pose settled")
    verdict = "failed" if failed else "check" if check else "ok"
    return {"verdict": verdict, "reasons": failed + check, "signals": signals}


def settled(final_step_mm: float | None, thresholds: ConfidenceThresholds = ConfidenceThresholds()) -> bool:
    """Whether a final stage stopped by its cap had settled: its last steps (``final_step_mm``, None: not known)
    under ``settled_step_mm``."""
    return final_step_mm is not None and final_step_mm < thresholds.settled_step_mm


def _partial_visibility(signals: dict, thresholds: ConfidenceThresholds) -> str | None:
    """The partial-visibility reason, or None: every view's vessels explained, part of the model
    unmatched in every view, by similar shares."""
    unmatched, uncovered = signals.get("unmatched_fraction"), signals.get("uncovered_fraction")
    if not unmatched or not uncovered or len(unmatched) < 2:
        return None  # one view cannot tell unfilled branches from a pose slid along its ray
    if not (all(value >= thresholds.partial_unmatched for value in unmatched.values())
            and all(value <= thresholds.partial_uncovered for value in uncovered.values())
            and max(unmatched.values()) - min(unmatched.values()) <= thresholds.partial_consistency):
        return None
    shares = " / ".join(f"{name} {value:.0%}" for name, value in unmatched.items())
    other = signals.get("part_runner_up")
    pose = ("the pose fits the filled vessels" if other is None else
            f"the pose is uncertain: another part of the model, placed {other['distance_mm']:.0f} mm away, matches the "
            f"filled vessels almost as well (score {other['score']:.2f}), and the unfilled vessels cannot tell them apart")
    return (f"the model has vessels the images do not show ({shares} of its silhouette outside the vessels, "
            "consistently across views) while every vessel shown is matched: partial filling or a model larger "
            f"than the run; {pose}")


def _images_hold_more(signals: dict, thresholds: ConfidenceThresholds) -> str | None:
    """The reason for images holding vessels the model does not, or None: in every view (two or more) at least
    ``more_uncovered`` of the vessels lie off the model while its silhouette lies on vessels (``partial_unmatched``).
    Every view: a territory or branches the model lacks show in both; a catheter or background can fill one view
    alone (the grey-level phantom's catheter: 16 % of the AP vessels, 8 % of the LAT's; its pose 0.02 mm off)."""
    unmatched, uncovered = signals.get("unmatched_fraction") or {}, signals.get("uncovered_fraction") or {}
    if len(uncovered) < 2 or not all(name in unmatched and uncovered[name] >= thresholds.more_uncovered
                                     and unmatched[name] < thresholds.partial_unmatched for name in uncovered):
        return None
    shares = " / ".join(f"{name} {value:.0%}" for name, value in uncovered.items())
    return (f"the images show vessels the model lacks ({shares} of the vessels farther than 2 px from the model) "
            "while the model lies on vessels: a model of one territory or without its small branches, or background "
            "in the segmentation (a catheter, bone); the pose fits the vessels the model holds, check that they are "
            "its own")


def _why_low(signals: dict, name: str, thresholds: ConfidenceThresholds) -> str:
    """Which way a view's overlap falls short: vessels the model lacks, model parts outside the vessels, or both."""
    unmatched = (signals.get("unmatched_fraction") or {}).get(name)
    uncovered = (signals.get("uncovered_fraction") or {}).get(name)
    if unmatched is None or uncovered is None:
        return "missing or extra vessels, or a wrong pose"
    if uncovered >= thresholds.missing_uncovered and unmatched < thresholds.partial_unmatched:
        return f"the images show vessels the model lacks ({uncovered:.0%} of the vessels unmatched)"
    if unmatched >= thresholds.partial_unmatched and uncovered <= thresholds.partial_uncovered:
        return (f"{unmatched:.0%} of the model outside the vessels in this view only; "
                "a wrong pose or a vessel the run did not fill")
    return (f"a wrong pose ({unmatched:.0%} of the model outside the vessels and "
            f"{uncovered:.0%} of the vessels unmatched)")
