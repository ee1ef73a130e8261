"""One registration job end to end: case in, result files out (used by the CLI and the service).

Writes into ``out_dir``: ``result.json``, ``overlay_{ap,lat}.png``, ``mask_{ap,lat}.png``
(the masks actually registered, 0/255), ``loss.png`` (loss per iteration) and, when
asked, ``animation.gif``.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Callable

import cv2
import numpy as np
import torch

from .overlay import loss_plot, overlay_image, write_png
from .registration import RegistrationCanceled, RegistrationOptions, RegistrationResult, register
from .render import Camera, render_hard_silhouette

__all__ = ["RegistrationCanceled", "run_registration_case", "write_outputs"]


def run_registration_case(
    case,
    options: RegistrationOptions,
    out_dir: Path,
    progress: Callable[[dict], None] | None = None,
    should_stop: Callable[[], bool] | None = None,
) -> dict:
    """Register a loaded case (``mesh``, ``masks``, ``rig``, ``warnings``) and write its outputs.

    Returns:
        The JSON-ready result dict (also written as ``result.json``).

    Raises:
        RegistrationCanceled: ``should_stop()`` returned True.
    """
    result = register(case.mesh, case.masks, case.rig, options, progress=progress, should_stop=should_stop)
    data = write_outputs(result, case.masks, Path(out_dir), case.mesh, case.rig, animation=options.animation)
    warnings = list(getattr(case, "warnings", []) or [])
    if warnings:
        data["warnings"] = warnings
        (Path(out_dir) / "result.json").write_text(json.dumps(data, indent=2))
    return data


def write_outputs(result: RegistrationResult, masks: dict[str, np.ndarray], out_dir: Path, mesh=None, rig=None, animation: bool = False) -> dict:
    """Write result.json, overlays and masks (and the animation) for a finished registration."""
    out_dir.mkdir(parents=True, exist_ok=True)
    data = result.to_dict()
    (out_dir / "result.json").write_text(json.dumps(data, indent=2))
    for name, view in result.views.items():
        write_png(out_dir / f"overlay_{name}.png", overlay_image(masks[name], view.initial_silhouette, view.silhouette))
        write_png(out_dir / f"mask_{name}.png", masks[name].astype(np.uint8) * 255)
    write_png(out_dir / "loss.png", loss_plot(result.loss_history))
    if animation and mesh is not None and rig is not None:
        write_animation(out_dir / "animation.gif", result, masks, mesh, rig)
    return data


def write_animation(path: Path, result: RegistrationResult, masks: dict[str, np.ndarray], mesh, rig, max_side: int = 320) -> None:
    """An animated GIF: both views side by side, one frame per recorded pose."""
    from PIL import Image

    vertices, faces = mesh.torch(torch.float64)
    frames = []
    for pose in [*result.pose_history, result.mesh_to_world]:
        panels = []
        for name in result.views:
            view = rig.views[name]
            scale = min(1.0, max_side / max(view.image_size))
            small = view.scaled(scale)
            silhouette = render_hard_silhouette(
                vertices, faces, torch.as_tensor(small.world_to_view @ pose)[None], Camera.from_view(small)
            )[0].numpy()
            target = cv2.resize(masks[name].astype(np.uint8), small.image_size, interpolation=cv2.INTER_NEAREST).astype(bool)
            initial = np.zeros_like(target)
            panels.append(overlay_image(target, initial, silhouette))
        height = max(p.shape[0] for p in panels)
        panels = [np.pad(p, ((0, height - p.shape[0]), (0, 0), (0, 0))) for p in panels]
        frames.append(Image.fromarray(cv2.cvtColor(np.concatenate(panels, axis=1), cv2.COLOR_BGR2RGB)))
    frames[0].save(path, save_all=True, append_images=frames[1:], duration=400, loop=0)
