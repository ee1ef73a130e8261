"""One registration's set-up, fixed before the first stage runs: the inputs checked, the starts (searched, or
drawn around the given pose), the problem, and the stage list (the pyramid's coarsest level set by the vessels'
extent)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from ..errors import DsaregInputError
from ..geometry.pose import validate_rigid
from ..geometry.rig import Rig
from ..mesh import TriangleMesh
from ..render.jacobian import jacobian_available
from ..vision.vessel_target import binary_mask, is_coverage
from .options import RegistrationOptions
from .parameterization import random_start_poses
from .problem import _Problem
from .schedule import COARSEST_SIDE_PX, Stage, build_schedule
from .search.initialization import Initialization
from .starts import _initialize
from .track import build_track_schedule

MIN_COARSE_OBJECT_PX = 48
"""After a pose search, pyramid levels where the vessels span fewer pixels than this are skipped."""


@dataclass
class _Setup:
    """What one registration runs: the problem, its views, the stage list (fixed before the first
    stage runs) and the starts."""

    problem: _Problem
    used_views: tuple[str, ...]
    initial: np.ndarray
    searched: Initialization | None
    """The pose search's :class:`~.initialization.Initialization`, or None when the starts came from a given pose."""
    stages: list[Stage]
    starts: np.ndarray
    tracking: bool


def _prepare(mesh: TriangleMesh, masks: dict[str, np.ndarray], rig: Rig, options: RegistrationOptions,
             device: torch.device) -> _Setup:
    """Check the inputs, find or draw the starts, and build the problem and its stage list."""
    used_views = ("ap", "lat") if options.configuration not in ("ap", "lat") else (options.configuration,)
    _check_inputs(masks, rig, used_views)
    initial = rig.initial_mesh_to_world
    if options.initial_mesh_to_world is not None:
        initial = validate_rigid(options.initial_mesh_to_world, field="options.initial_mesh_to_world", allow_mirror=False)
    targets, masks = masks, {name: binary_mask(target) for name, target in masks.items()}
    searched = _initialize(mesh, masks, rig, options)
    if searched is not None:
        initial = searched.poses[0]
    problem = _Problem(mesh, targets, rig, options, device, initial)
    # the partial searches' starts (the model holds more than the images); not those placed for images holding more
    problem.partial = searched is not None and searched.method.startswith("search+") and searched.method != "search+precise"
    if searched is not None and searched.fit_faces is not None:
        problem.fit_part(searched.fit_faces)
    longest = max(max(rig.views[name].image_size) for name in used_views)
    final_scale = min(1.0, options.working_size_px / longest) if options.working_size_px else 1.0
    shortest = min(min(rig.views[name].image_size) for name in used_views)
    tracking = options.mode == "track"
    side_px = round(shortest * final_scale)
    schedule = (
        build_track_schedule(used_views, side_px, options.max_iterations, jacobian_available(device)) if tracking
        else _ladder_schedule(options, side_px, masks, used_views, final_scale, jacobian_available(device))
    )
    stages = [Stage(**{**vars(stage), "scale": stage.scale * final_scale}) for stage in schedule]
    starts = searched.poses if searched is not None else random_start_poses(
        initial, problem.centre, 1 if tracking else options.starts, options.start_spread_deg, options.start_spread_mm,
        options.seed)
    return _Setup(problem, used_views, initial, searched, stages, starts, tracking)


def _ladder_schedule(options: RegistrationOptions, side_px: int, masks: dict[str, np.ndarray], used_views,
                     final_scale: float, jacobian: bool = False) -> list[Stage]:
    """The coarse-to-fine stages: the image's pyramid, its coarsest level set by the vessels' extent when that is
    what limits it (:func:`_coarsest_scale`), else by :func:`_pyramid_side_px`'s power-of-two rule."""
    coarsest = _coarsest_scale(side_px, masks, used_views, final_scale)
    side = side_px if coarsest is not None else _pyramid_side_px(side_px, masks, used_views, final_scale)
    return build_schedule(options.configuration, side, options.max_iterations, options.coarse_to_fine, options.refine,
                          coarsest, jacobian)


def _vessel_extent_px(masks: dict[str, np.ndarray], used_views) -> int:
    """The smallest over the views of the vessels' bounding-box side (px, full resolution)."""
    extent = []
    for name in used_views:
        rows, cols = np.nonzero(masks[name])
        extent.append(max(rows.max() - rows.min(), cols.max() - cols.min()) + 1)
    return int(min(extent))


def _pyramid_side_px(side_px: int, masks: dict[str, np.ndarray], used_views, final_scale: float) -> int:
    """Image side that sets the pyramid's depth: the coarsest level must still show the vessels
    (their bounding box ≥ MIN_COARSE_OBJECT_PX). A small tree at ~100 px loses its branches: after
    a pose search its coarse optimum could lie 10 mm from the truth (the phantom on a 384-px
    clinical rig), and from a given pose (the synthetic DICOM study: phantom at 256 px, 6° / 5 mm
    off identity) the half-size level handed on a pose whose border correction (measured there,
    −0.6 px on AP) left the final fit at 1.03° / ADD 0.15 mm instead of 0.40° / 0.08 mm. On the
    paper's mesh at 800 px the vessels span 630–750 px and the pyramid is the image-size one.
    Rounded down to a power of two; :func:`_coarsest_scale` gives the unrounded coarsest level."""
    extent = _vessel_extent_px(masks, used_views)
    halvings = max(0, int(np.floor(np.log2(extent * final_scale / MIN_COARSE_OBJECT_PX))))
    return min(side_px, int(COARSEST_SIDE_PX * 2**halvings))


def _coarsest_scale(side_px: int, masks: dict[str, np.ndarray], used_views, final_scale: float) -> float | None:
    """The scale (of the working image) at which the vessels span MIN_COARSE_OBJECT_PX, when the extent rather than
    the image size limits the pyramid (:func:`~.schedule.pyramid_scales`); else None. Not rounded to a power of two:
    rounded, a tree spanning 190 px at 512 px started at half size where one spanning 192 px starts at a quarter
    (4× the pixels per start and step; docs/benchmarks/clinical.md, rounds 10 and 11)."""
    scale = MIN_COARSE_OBJECT_PX / (_vessel_extent_px(masks, used_views) * final_scale)
    return scale if scale <= 0.5 and scale * side_px > COARSEST_SIDE_PX else None


def _check_inputs(masks: dict[str, np.ndarray], rig: Rig, used_views: tuple[str, ...]) -> None:
    for name in used_views:
        if name not in rig.views:
            raise DsaregInputError(f"the configuration needs the '{name}' view", field=f"geometry.views.{name}")
        if name not in masks:
            raise DsaregInputError(f"no vessel mask for the '{name}' view", field=name)
        expected = rig.views[name].image_size[::-1]
        if tuple(masks[name].shape) != tuple(expected):
            raise DsaregInputError(
                f"mask is {masks[name].shape[1]}x{masks[name].shape[0]} px but the geometry says "
                f"{expected[1]}x{expected[0]}", field=name, accepted="images of the size given in the geometry",
            )
        if is_coverage(masks[name]) and not (np.all(np.isfinite(masks[name])) and masks[name].min() >= 0.0 and masks[name].max() <= 1.0):
            raise DsaregInputError("a vessel coverage map must lie in [0, 1]", field=name, accepted="a bool mask or coverage in [0, 1]")
        if not (masks[name] >= 0.5).any():
            raise DsaregInputError("the vessel mask is empty: nothing to register to", field=name)
