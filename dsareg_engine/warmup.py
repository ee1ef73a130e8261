"""Warm-up of a worker process: one tiny registration through every step a job takes.

A fresh process pays ~1.5 CPU-s on its first job for lazy imports and first-use set-up that
the renderer's warm-up does not reach: torch's optimizers import ``torch._dynamo``, the loss
plot imports matplotlib and builds its font cache, the DICOM writer imports pydicom, the image
readers their codecs. Measured on 2 cores: first job 2.1 CPU-s, the next ones 0.5 CPU-s (128 px
phantom, 60 iterations). :func:`warm_up_job` pays this before the worker takes its first job.
"""

from __future__ import annotations

import io
import json
from pathlib import Path

WARM_UP_SIZE_PX = 32
WARM_UP_ITERATIONS = 2


def phantom_case_files(work_dir: Path, size_px: int = WARM_UP_SIZE_PX) -> dict[str, bytes | str]:
    """The phantom seen by the paper rig shrunk to ``size_px``: ``{"mesh", "ap", "lat"}`` file bytes
    (OBJ, PNG masks) and ``"geometry"`` (JSON text), as a client would upload them."""
    import numpy as np
    import torch
    from PIL import Image

    from .geometry.spec import load_rig
    from .simulation.phantom import make_vessel_phantom
    from .render import Camera, render_hard_silhouette

    rig = load_rig("paper")
    views = {name: view.resized(size_px, size_px) for name, view in rig.views.items()}
    mesh = make_vessel_phantom()
    mesh.save(work_dir / "phantom.obj")
    files: dict[str, bytes | str] = {"mesh": (work_dir / "phantom.obj").read_bytes()}
    for name, view in views.items():
        mesh_to_view = torch.as_tensor(view.world_to_view[None], dtype=torch.float32)
        mask = render_hard_silhouette(*mesh.torch(), mesh_to_view, Camera.from_view(view))[0].numpy()
        buffer = io.BytesIO()
        Image.fromarray(mask.astype(np.uint8) * 255).save(buffer, format="PNG")
        files[name] = buffer.getvalue()
    files["geometry"] = json.dumps({"views": {n: v.to_dict() for n, v in views.items()},
                                    "initial_mesh_to_world": rig.initial_mesh_to_world.tolist()})
    return files


def warm_up_job(work_dir: Path) -> dict:
    """Load, register (``WARM_UP_ITERATIONS`` iterations), write every output and the DICOM results
    of a tiny phantom case in ``work_dir``, as a job does; returns the result dict."""
    from .geometry.spec import parse_geometry
    from .io.case import CaseFiles
    from .pipeline import run_case

    work_dir = Path(work_dir)
    files = phantom_case_files(work_dir)
    case_files = CaseFiles(mesh=files["mesh"], mesh_name="mesh.obj", ap=files["ap"], ap_name="ap.png",
                           lat=files["lat"], lat_name="lat.png", geometry=parse_geometry(files["geometry"]))
    return run_case(case_files, {"starts": 1, "max_iterations": WARM_UP_ITERATIONS}, work_dir, label="warm-up",
                    dicom="required")


__all__ = ["WARM_UP_ITERATIONS", "WARM_UP_SIZE_PX", "phantom_case_files", "warm_up_job"]
