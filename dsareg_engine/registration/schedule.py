"""Coarse-to-fine stage schedules for each configuration of the paper's Table 1."""

from __future__ import annotations

from dataclasses import dataclass

COARSEST_SIDE_PX = 96
"""The coarsest level is the largest power-of-two reduction keeping this many pixels per side."""
PLATEAU_TOLERANCE = 1e-3
"""An Adam stage has converged when its best loss improved by less than this fraction over
the solver's patience window."""
SWITCH_TOLERANCE = 1e-2
"""Plateau used by the single-view phase of ``*_then_*`` configurations before the second
view's λ is switched on. One view leaves a valley along depth and out-of-plane rotation
that never flattens at PLATEAU_TOLERANCE (measured on the paper's mesh: LAT alone still
gaining 0.3 % per 15 iterations after 300), so the stricter rule only burns time there."""
ADAM_SIGMA_PX = 0.25
"""Edge softness of the renders at the Adam levels of a pyramid."""
INTERMEDIATE_TOLERANCE = 1e-2
"""Plateau of the Adam levels between the coarsest and the final L-BFGS stage."""
FINAL_SIGMA_PX = 0.1
"""Sharp edges for the final fit. Dense meshes aggregate many faces near the contour, which
widens the soft silhouette by a fraction of σ and biases the pose toward smaller
silhouettes; measured on the paper's mesh at 800 px, ADD 0.0081 mm at σ = 0.25 and 0.0025 mm
at σ = 0.1 (the phantom at 400 px: 0.135 → 0.011 mm)."""


@dataclass(frozen=True)
class Stage:
    """One optimization stage.

    Attributes:
        name: label in metrics and progress (``"ap:1/8"``, ``"ap+lat:1/1"``...).
        scale: image scale relative to the working resolution.
        sigma_px: silhouette edge softness at this level (px of the level's image).
        blur_px: Gaussian blur of the target at this level (px), widening capture.
        views: active views (λ = 1), the others have λ = 0.
        optimizer: ``"adam"`` (robust, batched over starts), ``"lbfgs"`` (tight final fit) or
            ``"gauss_newton"`` (Levenberg–Marquardt on one start from per-pixel Jacobians, CPU).
        level_of_detail: render a decimated mesh (None: Adam stages only).
        max_iterations: iteration cap (Adam steps, or L-BFGS evaluations).
        learning_rate: Adam step in mm (pose increments are scaled to mm).
        all_starts: optimize every start (True) or only the best so far.
        add_initial_starts: before this stage, add the initial starts back as candidates
            (sequential configurations: the single-view phase may have drifted along the
            directions one view cannot see).
        plateau_tolerance: Adam stops when the best loss improves by less than this
            fraction over the patience window.
        float64: render in float64 with exact transcendentals (None: for L-BFGS stages only).
        pose_tolerance: L-BFGS stop on pose change (mm units; None: the solver's LBFGS_POSE_TOLERANCE).
        plateau_window: Adam only: > 0 stops when the mean best loss of the last this many steps is not
            WINDOW_TOLERANCE below the mean of the window before (0: the solver's patience rule).
        handover: the Levenberg–Marquardt stage at the last Adam level that hands the kept start to the
            full-size fit (see HANDOVER_POSE_TOLERANCE): the fine-stage work (border, partial check) waits for
            the final stage.
    """

    name: str
    scale: float
    sigma_px: float
    blur_px: float
    views: tuple[str, ...]
    optimizer: str
    max_iterations: int
    learning_rate: float
    all_starts: bool
    add_initial_starts: bool = False
    plateau_tolerance: float = PLATEAU_TOLERANCE
    float64: bool | None = None
    pose_tolerance: float | None = None
    level_of_detail: bool | None = None
    plateau_window: int = 0
    handover: bool = False


PLATEAU_WINDOW = 4
WINDOW_TOLERANCE = 1e-2
"""The coarsest Adam level stops when the mean of its best loss over PLATEAU_WINDOW steps falls by less than this
fraction from the window before. At its 0.8-mm step the starts near a minimum jitter by a few % of the loss, and
a stop on a new best of 0.1 % within 8 steps ended the level after 12–67 steps, by when the jitter happened to
touch a new best: a draw moved by a few border pixels of the target (docs/benchmarks/clinical.md, round 10)."""
HANDOVER_BLUR_PX = 1.0
HANDOVER_POSE_TOLERANCE = 0.03
"""Two-view ladders on the CPU (the Jacobian kernel, :mod:`.gauss_newton`) end with Levenberg–Marquardt instead of
L-BFGS: first at the last Adam level's size, blurred by HANDOVER_BLUR_PX, stopped at this pose change (mm; the tracking
schedule's coarse stop), then at full size as sharp as L-BFGS was (FINAL_SIGMA_PX, float64, the same pose stop).
The last Adam level handed over a pose 0.3–0.8 mm off on the paper's mesh at 800 px; L-BFGS took 14–17 full-size
evaluations from there (two or three of them overshooting line-search probes), Levenberg–Marquardt takes 2–3
iterations at quarter size and 4 at full size, each about two L-BFGS evaluations' work; ADD the same to 4 decimals.
The hand-over replaces that last Adam level (the level before it hands over directly, 1–3 mm off): Adam spent 9–23
steps there (on every start still distinct, 1–4 on Table 1) to bring the pose within reach of the hand-over, which now
takes 3–5 iterations (12 once) on the one start kept; the full-size fit's iterations and ADD the same (Table 1, 21
poses; autoinit, paper and phantom)."""
FINER_LEVEL_RATIO = 1.5
"""A level above a fractional coarsest one is kept when it is at least this much finer (else it nearly repeats it)."""


def pyramid_scales(image_side_px: int, coarsest_scale: float | None = None) -> list[float]:
    """Scales 1/2^k … 1 with the coarsest level at least COARSEST_SIDE_PX on its short side.

    ``coarsest_scale`` (from the vessels' extent, see ``preparation._coarsest_scale``): when it is finer than the
    image's coarsest level and at most 0.5, it becomes the coarsest level, replacing the power-of-two levels
    below it and a next one less than FINER_LEVEL_RATIO finer; the ladder's coarsest level then follows the
    extent continuously instead of jumping by a factor 2 (4× the pixels of every start's renders) when the
    extent crosses 2^k × 48 px.
    """
    scales = [1.0]
    while image_side_px * scales[0] / 2 >= COARSEST_SIDE_PX:
        scales.insert(0, scales[0] / 2)
    if coarsest_scale is None or coarsest_scale <= scales[0] or coarsest_scale > 0.5:
        return scales
    return [coarsest_scale] + [scale for scale in scales if scale >= FINER_LEVEL_RATIO * coarsest_scale]


def _ladder(views: tuple[str, ...], scales: list[float], max_iterations: int, final: bool, jacobian: bool = False) -> list[Stage]:
    label = "+".join(views)
    stages = []
    if len(scales) == 1 and not final:  # single level, no refinement: plain Adam at full size
        return [Stage(f"{label}:1/{round(1 / scales[0])}", scales[0], 0.5, 0.0, views, "adam", max_iterations, 0.1, True)]
    if final and len(scales) == 1:  # one level: blurred Adam to settle, then sharp L-BFGS to converge
        scales = scales + [scales[-1]]
    # With a pyramid, L-BFGS at full size starts from the last Adam level: a full-size Adam stage
    # before it cost ~2 s (20+ iterations of 800² renders, blurred) on the paper's mesh and saved
    # L-BFGS only 1–2 evaluations (9 → 10–11), accuracy unchanged. With four levels or more the
    # half-size level goes too (Adam up to a quarter of full size): it cost ~24 % of the CPU time
    # and L-BFGS needed 10–16 instead of 9–12 evaluations after it; −22 % CPU, same accuracy.
    if final and len(scales) >= 4:
        scales = scales[:-2] + [scales[-1]]
    for index, scale in enumerate(scales):
        last = final and index == len(scales) - 1
        # Levels are set by their place in the ladder: the coarsest (~100 px) always gets
        # the widest blur and the largest steps, whatever the full image size.
        # Blur at the coarsest level (2 px) and at quarter size (1 px); none from half size up:
        # capture is settled by then, and blurring 400² renders cost more than rendering them.
        blur_px = 2.0 if index == 0 and not last else (1.0 if scale <= 0.25 and not last else 0.0)
        stages.append(
            Stage(
                name=f"{label}:1/{round(1 / scale)}" + (":refine" if last else ""),
                scale=scale,
                # σ sets the renderer's cost (faces × disc of radius ~7σ). Under a blur of 1–2 px the
                # edge softness hardly matters: σ 0.25 instead of 0.5 there cost ~15 % less CPU per
                # registration, same capture (12–20 mm starts) and accuracy; at the unblurred half-size
                # level it also left L-BFGS 9–10 instead of 10–13 evaluations (~6 % less CPU).
                sigma_px=FINAL_SIGMA_PX if last else ADAM_SIGMA_PX,
                blur_px=blur_px,
                views=views,
                optimizer="lbfgs" if last else "adam",
                max_iterations=min(max_iterations, 60) if last else max_iterations,
                learning_rate=0.8 if index == 0 else 0.2 / 2 ** max(0, index - 1),
                all_starts=index == 0 or scale <= 0.25,
                # Levels after the coarsest only hand a pose to the next, finer one: a 1 % plateau
                # suffices (measured on the paper's mesh: the half-size level took 10–13 instead of
                # 11–29 iterations, same L-BFGS evaluations and final accuracy).
                plateau_tolerance=PLATEAU_TOLERANCE if index == 0 or last else INTERMEDIATE_TOLERANCE,
                # A single-level ladder (small images) keeps the patience rule: its one Adam level carries the whole
                # capture from a given or mirrored start (measured: a mirrored 160-px phantom was no longer named).
                plateau_window=PLATEAU_WINDOW if not last and len(set(scales)) > 1 else 0,
            )
        )
    # Only after two Adam levels or more (the last of them goes, the hand-over takes its size): a single (coarsest)
    # level hands over a pose from its 2-px blur and 0.8-mm steps, from which Levenberg–Marquardt's σ-long full-size
    # steps took longer than L-BFGS (the phantom at 512 px, no initial pose: 6 + 31 iterations against 27 L-BFGS
    # evaluations, +10 % CPU).
    if final and jacobian and len(views) == 2 and sum(stage.optimizer == "adam" for stage in stages) >= 2:
        stages[-2:] = _gauss_newton_finish(stages[-2], stages[-1], max_iterations)
    return stages


def _gauss_newton_finish(adam: Stage, final: Stage, max_iterations: int) -> list[Stage]:
    """The last Adam level ``adam`` and the L-BFGS stage ``final`` replaced by Levenberg–Marquardt at ``adam``'s size,
    then at full size (see HANDOVER_POSE_TOLERANCE)."""
    handover = Stage(
        name=f"{adam.name}:lm", scale=adam.scale, sigma_px=ADAM_SIGMA_PX, blur_px=HANDOVER_BLUR_PX, views=final.views,
        optimizer="gauss_newton", max_iterations=min(max_iterations, 60), learning_rate=adam.learning_rate,
        all_starts=False, pose_tolerance=HANDOVER_POSE_TOLERANCE, float64=False, level_of_detail=True, handover=True,
    )
    return [handover, Stage(**{**vars(final), "optimizer": "gauss_newton", "max_iterations": min(max_iterations, 40),
                               "float64": True, "level_of_detail": False})]


def build_schedule(
    configuration: str, image_side_px: int, max_iterations: int, coarse_to_fine: bool = True, refine: bool = True,
    coarsest_scale: float | None = None, jacobian: bool = False,
) -> list[Stage]:
    """Stages for ``ap``, ``lat``, ``simultaneous``, ``ap_then_lat`` or ``lat_then_ap``.

    Sequential configurations run the whole ladder on the first view, then switch the
    second view's λ on and repeat the finer half of the ladder with both views.
    ``coarse_to_fine=False`` keeps only the full-size level; ``refine=False`` drops the
    final L-BFGS stage (both exist to measure what each contributes); ``coarsest_scale``: see :func:`pyramid_scales`;
    ``jacobian`` (the Jacobian kernel runs here): two-view pyramids end with Levenberg–Marquardt (see
    HANDOVER_POSE_TOLERANCE).
    """
    scales = pyramid_scales(image_side_px, coarsest_scale) if coarse_to_fine else [1.0]
    if configuration in ("ap", "lat"):
        return _ladder((configuration,), scales, max_iterations, final=refine)
    if configuration == "simultaneous":
        return _ladder(("ap", "lat"), scales, max_iterations, final=refine, jacobian=jacobian)
    first = configuration.split("_then_")[0]
    if configuration not in ("ap_then_lat", "lat_then_ap"):
        raise ValueError(f"unknown configuration {configuration!r}")
    # Phase 1: the first view alone up to half size. Phase 2 (λ of the second view on): both
    # views from the second level up, with the initial starts competing again with phase 1's
    # result, because one view leaves depth and out-of-plane rotation weakly determined.
    stages = [Stage(**{**vars(stage), "plateau_tolerance": SWITCH_TOLERANCE, "plateau_window": 0})
              for stage in _ladder((first,), scales[:-1] or scales, max_iterations, final=False)]
    both = _ladder(("ap", "lat"), scales[1:] if len(scales) > 2 else scales, max_iterations, final=refine, jacobian=jacobian)
    both[0] = Stage(**{**vars(both[0]), "all_starts": True, "add_initial_starts": True, "plateau_window": 0})
    return stages + both
