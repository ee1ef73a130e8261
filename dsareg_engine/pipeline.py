"""One registration job end to end: case in, result files out (used by the CLI and the service).

:func:`run_case` is the whole job in one call (files → case → registration → outputs, DICOM
included; the service's workers call it); :func:`run_registration_case` starts from a loaded case.

Writes into ``out_dir``: ``result.json``, ``overlay_{ap,lat}.png``, ``mask_{ap,lat}.png``
(the masks actually registered, 0/255), ``loss.png`` (loss per iteration) and, when
asked, ``animation.gif``. Overlays show the DSA image (or the mask) with the initial and
registered contours, a caption (view, Dice, verdict, job) and a scale bar in mm at the
vessel's depth; the animation runs from the initial contour to the registered one with each
frame's stage and iteration.
"""

from __future__ import annotations

import dataclasses
import json
import logging
from collections.abc import Callable
from pathlib import Path
from typing import Literal

import cv2
import numpy as np
import torch

from . import artifacts
from .errors import DsaregInputError
from .io.case import Case, CaseFiles, load_case_files
from .io.dicom_identity import DicomSources
from .io.limits import DEFAULT_LIMITS, InputLimits
from .io.model_cache import ModelStore
from .io.input_decisions import InputDecision, with_close_calls
from .io.review_files import write_model_json, write_view_files
from .io.view_roles import views_swapped
from .io.volume_kind import VolumeReading
from .metrics import dice
from .overlay import Caption, crop_box, overlay_image, write_png
from .plots import loss_figure
from .registration import RegistrationOptions
from .registration.result import RegistrationResult
from .registration.motion import sequential_runs
from .registration.solver import RegistrationCanceled, register
from .registration.view_swap import swap_hint
from .registration.options import image_reading, parse_options
from .registration.partial import PARTIAL_UNMATCHED, unmatched_pixels
from .registration.progress import REGISTRATION_SHARE
from .render import Camera, render_hard_silhouette

__all__ = ["RegistrationCanceled", "run_case", "run_registration_case", "write_outputs"]

log = logging.getLogger(__name__)


DICOM_FRACTION = 0.98
"""Progress while the DICOM results are written (after the PNGs and the animation)."""

DicomOutputs = Literal["off", "best_effort", "required"]
"""DICOM results of :func:`run_case`: none; written when possible (a failure becomes a warning); or
required (a failure raises: the caller stores them in a PACS)."""


def run_case(files: CaseFiles, options: RegistrationOptions | dict | None, out_dir: Path, *,
             limits: InputLimits = DEFAULT_LIMITS, progress: Callable[[dict], None] | None = None,
             should_stop: Callable[[], bool] | None = None, label: str | None = None,
             dicom: DicomOutputs = "best_effort", model_store: ModelStore | None = None) -> dict:
    """Files in, files out: read the case, register it, write every output into ``out_dir``.

    The one call an application makes for a whole job (the service's workers do). Writes what
    :func:`run_registration_case` writes, and with ``dicom`` the DICOM results
    (:func:`dsareg_engine.io.dicom_out.write_dicom_outputs`, listed in ``result["dicom"]["instances"]``).

    Returns:
        The result dict, with the case's warnings (``files.warnings`` first) under ``"warnings"``.

    Raises:
        DsaregInputError: the inputs or options cannot be used (``field`` names which).
        RegistrationCanceled: ``should_stop()`` returned True.
    """
    options = options if isinstance(options, RegistrationOptions) else parse_options(options)
    case = load_case_files(files, options.segmentation, limits, reading=image_reading(options),
                           volume_reading=VolumeReading.from_options(options), mesh_units=options.mesh_units,
                           model_store=model_store)
    if views_swapped(case.decisions):  # the files follow the views they are (hemodynamics reads them again)
        files = dataclasses.replace(files, ap=files.lat, lat=files.ap, ap_name=files.lat_name, lat_name=files.ap_name)
    if options.hemodynamics:
        from .hemodynamics.intake import check_timed_runs

        check_timed_runs(files)
    if should_stop is not None and should_stop():
        raise RegistrationCanceled("stopped before start")
    if progress is not None:
        progress({"stage": "start", "iteration": 0, "loss": None, "fraction": 0.0})
    data = run_registration_case(case, options, out_dir, progress=progress, should_stop=should_stop, label=label)
    write_model_json(Path(out_dir), files.mesh, files.mesh_name, case.mesh, data)  # the review page's 3D scene
    if options.hemodynamics:
        _hemodynamics(files, case, data, Path(out_dir), progress)
    if dicom != "off":
        if progress is not None:
            progress({"stage": "dicom", "iteration": 0, "loss": None, "fraction": DICOM_FRACTION})
        _write_dicom(case.sources, data, Path(out_dir), required=dicom == "required")
    return data


def _hemodynamics(files: CaseFiles, case: Case, data: dict, out_dir: Path,
                  progress: Callable[[dict], None] | None) -> None:
    """``options.hemodynamics``: arrival times on the registered model (:mod:`dsareg_engine.hemodynamics`)."""
    from .hemodynamics.run import attach

    if progress is not None:
        progress({"stage": "hemodynamics", "iteration": 0, "loss": None, "fraction": OUTPUTS_DONE})
    attach(files, case, data, out_dir)


def _write_dicom(sources: DicomSources, data: dict, out_dir: Path, *, required: bool) -> None:
    """DICOM results next to the PNGs; the DICOM inputs' patient and study (``case.sources``) when there are any."""
    from .io.dicom_out import write_dicom_outputs

    if sources.unreadable:
        if required:
            raise DsaregInputError("the DICOM identity (patient, study, UIDs) of the input cannot be read",
                                   field=sources.unreadable[0])
        log.warning("the DICOM headers of the inputs could not be read; DICOM results start a new study")
        sources = DicomSources()
    try:
        tracked = (data.get("metrics", {}).get("tracking") or {}).get("views")
        unfitted = tuple(view for view in ("ap", "lat") if tracked is not None and view not in tracked)
        data["dicom"] = {"instances": write_dicom_outputs(out_dir, data["mesh_to_world"], sources, out_dir,
                                                          unfitted=unfitted)}
        if "hemodynamics" in data:
            from .hemodynamics.dicom import write_parametric_dicom

            data["dicom"]["instances"].update(write_parametric_dicom(out_dir, sources))
    except Exception as exc:
        if required:
            raise
        log.warning("DICOM outputs not written (%s)", exc)
        data.setdefault("warnings", []).append("DICOM outputs could not be written")


def run_registration_case(
    case: Case,
    options: RegistrationOptions,
    out_dir: Path,
    progress: Callable[[dict], None] | None = None,
    should_stop: Callable[[], bool] | None = None,
    label: str | None = None,
) -> dict:
    """Register a loaded case (``mesh``, ``masks``, ``rig``, ``warnings``) and write its outputs.

    Args:
        label: shown in the overlays' captions (the service passes ``"job <id>"``).

    Returns:
        The JSON-ready result dict (also written as ``result.json``), with the case's warnings
        under ``"warnings"`` when there are any (the one place they join the result).

    Raises:
        RegistrationCanceled: ``should_stop()`` returned True.
    """
    result = register(case.mesh, case.fitted, case.rig, options, progress=progress, should_stop=should_stop)
    if not any(decision.what == "view roles" for decision in case.decisions):  # no header named the views
        swap_hint(case.mesh, case.fitted, case.rig, result, options)
    acquisition = case.acquisition.to_dict() if case.acquisition is not None else None
    one_plane = options.mode == "track" and options.configuration in ("ap", "lat")  # the other run is an earlier one
    if acquisition is not None and acquisition["sequential"] and not one_plane:  # a pose per run, the motion between
        acquisition = sequential_runs(case.mesh, case.fitted, case.rig, result, acquisition, options.device)
    return write_outputs(result, case.masks, Path(out_dir), case.mesh, case.rig, animation=options.animation,
                         images=case.images, label=label, progress=progress, warnings=case.warnings,
                         readings=case.readings, volume=case.volume.to_dict() if case.volume is not None else None,
                         decisions=case.decisions, acquisition=acquisition)


def verdict_of(data: dict) -> tuple[str, bool | None]:
    """Short verdict text and whether it is good (True), bad (False) or to be checked (None).

    Reads the confidence verdict (``metrics.confidence.verdict``: ok / check / failed, see
    :mod:`dsareg_engine.registration.confidence`); results without one fall back to
    ``metrics.converged``.
    """
    metrics = data.get("metrics") or {}
    verdict = (metrics.get("confidence") or {}).get("verdict")
    if isinstance(verdict, str) and verdict:
        return verdict, {"ok": True, "failed": False}.get(verdict)
    converged = metrics.get("converged")
    if converged is None:
        return "", None
    return ("converged" if converged else "NOT converged"), bool(converged)


def mm_per_pixel_at_mesh(view, mesh_to_view: np.ndarray, mesh=None) -> float | None:
    """Pixel size in mm at the depth of the mesh's centre (what a scale bar on the image means)."""
    centre = np.append(np.asarray(mesh.centroid, float), 1.0) if mesh is not None else np.array([0.0, 0.0, 0.0, 1.0])
    depth = float((np.asarray(mesh_to_view) @ centre)[2])
    if not np.isfinite(depth) or depth <= 0 or not view.sid_mm:
        return None
    return float(np.mean(view.pixel_spacing_mm)) * depth / float(view.sid_mm)


def write_outputs(result: RegistrationResult, masks: dict[str, np.ndarray], out_dir: Path, mesh=None, rig=None,
                  animation: bool = False, *, images: dict[str, np.ndarray] | None = None, label: str | None = None,
                  progress: Callable[[dict], None] | None = None, warnings: list[str] | None = None,
                  readings: dict[str, dict] | None = None, volume: dict | None = None,
                  decisions: list[InputDecision] | None = None, acquisition: dict | None = None) -> dict:
    """Write result.json (with ``warnings`` when any, ``image_reading``: what was read from each multi-frame XA
    run, ``volume``: what was read from a volume input, and ``input_decisions``: the decisions about the inputs,
    close calls lowering the verdict to ``check``; ``acquisition``: whether the runs were acquired together and, when
    not, each run's pose, :mod:`.registration.motion`), overlays, masks and the loss plot (and the
    animation) for a finished registration."""
    out_dir.mkdir(parents=True, exist_ok=True)
    data = result.to_dict()
    if volume:
        data["volume"] = volume
    if acquisition:
        data["acquisition"] = acquisition
    if warnings:
        data["warnings"] = [str(warning) for warning in warnings]
    if readings:
        data["image_reading"] = readings
    data = with_close_calls(data, list(decisions or []))
    report = _outputs_progress(progress, len(result.views) + 2)
    report()
    if rig is not None:  # the image registered, outline layers, detector geometry (review page)
        write_view_files(out_dir, result, masks, images, rig, {name: mm_per_pixel_at_mesh(rig.views[name], v.mesh_to_view, mesh)
                                                               for name, v in result.views.items()}, data)
    (out_dir / artifacts.RESULT_JSON).write_text(json.dumps(data, indent=2))
    verdict, ok = verdict_of(data)
    for name, view in result.views.items():
        report()
        scale = mm_per_pixel_at_mesh(rig.views[name], view.mesh_to_view, mesh) if rig is not None else None
        unmatched = unmatched_pixels(view.silhouette, masks[name])
        shown = unmatched if unmatched.sum() >= PARTIAL_UNMATCHED * max(1, view.silhouette.sum()) else None
        caption = Caption(view=name, dice=view.dice, verdict=verdict, ok=ok, job=label, mm_per_px=scale,
                          frame=frame_text((readings or {}).get(name)),
                          unmatched_label=None if shown is None else "unfilled")
        background = (images or {}).get(name)
        write_png(out_dir / artifacts.overlay_png(name),
                  overlay_image(masks[name], view.initial_silhouette, view.silhouette, background, caption=caption,
                                unmatched=shown))
        write_png(out_dir / artifacts.mask_png(name), masks[name].astype(np.uint8) * 255)
    report()
    write_png(out_dir / artifacts.LOSS_PNG, loss_figure(result.loss_history, title=f"Loss per iteration{' - ' + label if label else ''}"))
    if animation and mesh is not None and rig is not None:
        if progress is not None:
            progress({"stage": "animation", "iteration": 0, "loss": None, "fraction": OUTPUTS_DONE})
        write_animation(out_dir / artifacts.ANIMATION_GIF, result, masks, mesh, rig, images=images, label=label)
    return data


OUTPUTS_DONE = REGISTRATION_SHARE + 0.5 * (1.0 - REGISTRATION_SHARE)
"""Progress when the PNGs are written; the animation, the DICOM results and storing fill the rest."""


def _outputs_progress(progress: Callable[[dict], None] | None, steps: int) -> Callable[[], None]:
    """A ``report()`` that moves the stage ``outputs`` from REGISTRATION_SHARE to OUTPUTS_DONE in ``steps`` calls."""
    done = [0]

    def report() -> None:
        if progress is not None:
            fraction = REGISTRATION_SHARE + (OUTPUTS_DONE - REGISTRATION_SHARE) * done[0] / max(1, steps - 1)
            progress({"stage": "outputs", "iteration": done[0], "loss": None, "fraction": min(OUTPUTS_DONE, fraction)})
        done[0] += 1

    return report


def frame_text(reading: dict | None) -> str | None:
    """What the overlay says about the frame used (``None`` for a single image)."""
    if not reading or reading.get("frames", 1) <= 1:
        return None
    if reading.get("combined") == "minip":
        used = reading.get("frame_indices") or []
        text = f"MinIP of frames {used[0]}-{used[-1]}" if used else "MinIP"
    elif reading.get("combined") == "arterial":
        used = reading.get("frame_indices") or []
        text = f"arterial phase, frames {used[0]}-{used[-1]}" if used else "arterial phase"
    else:
        text = f"frame {reading.get('frame_index')}"
    text += f" of {reading['frames']}"
    if reading.get("run") == "native":
        masks = reading.get("mask_frame_indices") or []
        text += f" - mask {','.join(str(m) for m in masks)}"
    return text


MIN_FRAMES = 24
MAX_FRAMES = 48


def animation_frames(result: RegistrationResult) -> list[tuple[str, int, np.ndarray]]:
    """``(stage, iteration, pose)`` frames: the initial pose, up to MAX_FRAMES along the way (the
    last iteration of every stage included), the registered pose; at least MIN_FRAMES."""
    recorded = list(result.frames)
    if len(recorded) <= 1:  # no per-iteration record: one frame per stage
        recorded = [("initial", 0, result.initial_mesh_to_world)]
        recorded += [(name, len(losses), pose) for (name, losses), pose in zip(result.loss_history, result.pose_history[1:])]
    first, path = recorded[0], recorded[1:]
    if len(path) > MAX_FRAMES:
        last_of_stage = {i for i in range(len(path)) if i == len(path) - 1 or path[i + 1][0] != path[i][0]}
        picks = set(np.linspace(0, len(path) - 1, MAX_FRAMES - len(last_of_stage)).round().astype(int).tolist())
        path = [path[i] for i in sorted(picks | last_of_stage)]
    frames = [first, *path, ("registered", path[-1][1] if path else 0, result.mesh_to_world)]
    while len(frames) < MIN_FRAMES:  # hold the first and last frames (a short run still plays readably)
        frames.insert(0, first)
        if len(frames) < MIN_FRAMES:
            frames.append(frames[-1])
    return frames


def write_animation(path: Path, result: RegistrationResult, masks: dict[str, np.ndarray], mesh, rig, max_side: int = 320,
                    *, images: dict[str, np.ndarray] | None = None, label: str | None = None) -> None:
    """An animated GIF: both views side by side, from the initial contour to the registered one,
    each frame captioned with its stage and iteration."""
    from PIL import Image

    vertices, faces = mesh.torch(torch.float64)
    initial_pose = result.initial_mesh_to_world
    small_views, targets, backgrounds, initials, boxes = {}, {}, {}, {}, {}
    for name in result.views:
        view = rig.views[name]
        scale = min(1.0, max_side / max(view.image_size))
        small = view.scaled(scale)
        small_views[name] = small
        targets[name] = cv2.resize(masks[name].astype(np.uint8), small.image_size, interpolation=cv2.INTER_NEAREST).astype(bool)
        image = (images or {}).get(name)
        if image is not None and len(np.unique(image[::4, ::4])) <= 2:
            image = None  # a mask: drawn as the target itself
        backgrounds[name] = None if image is None else cv2.resize(image.astype(np.float32), small.image_size,
                                                                    interpolation=cv2.INTER_AREA)
        initials[name] = _silhouette(vertices, faces, small, initial_pose)
        # one region per view for the whole animation: the target and the initial and final contours
        boxes[name] = crop_box([targets[name], initials[name], _silhouette(vertices, faces, small, result.mesh_to_world)])
    frames, durations = [], []
    sequence = animation_frames(result)
    for number, (stage, iteration, pose) in enumerate(sequence):
        panels = []
        for name in result.views:
            small = small_views[name]
            current = _silhouette(vertices, faces, small, pose)
            caption = frame_caption(result, name, stage, iteration, f"{number + 1}/{len(sequence)}",
                                    dice(current, targets[name]))
            panels.append(overlay_image(targets[name], initials[name], current, backgrounds[name], caption=caption,
                                        box=boxes[name], display_side=max_side))
        height = max(p.shape[0] for p in panels)
        panels = [np.pad(p, ((height - p.shape[0], 0), (0, 0), (0, 0)), constant_values=40) for p in panels]
        frames.append(Image.fromarray(cv2.cvtColor(np.concatenate(panels, axis=1), cv2.COLOR_BGR2RGB)))
        durations.append(1200 if number in (0, len(sequence) - 1) else 150)
    frames[0].save(path, save_all=True, append_images=frames[1:], duration=durations, loop=0, optimize=False)


def frame_caption(result: RegistrationResult, view: str, stage: str, iteration: int, counter: str,
                  preview_dice: float) -> Caption:
    """The caption of one animation frame. Frames along the way show the Dice of their downscaled
    preview; the registered frame shows the result's own (full-resolution) Dice, the number the
    result reports, so the last frame and ``result.views[view].dice`` agree."""
    text = stage if stage in ("initial", "registered") else f"stage {stage}, iteration {iteration}"
    if stage == "registered":
        return Caption(view=view, dice=result.views[view].dice, stage=f"{counter}  {text}", final_label="registered",
                       dice_label="Dice")
    return Caption(view=view, dice=preview_dice, stage=f"{counter}  {text}", final_label="current",
                   dice_label="preview Dice")


def _silhouette(vertices, faces, view, pose: np.ndarray) -> np.ndarray:
    return render_hard_silhouette(vertices, faces, torch.as_tensor(view.world_to_view @ pose)[None],
                                  Camera.from_view(view))[0].numpy()
