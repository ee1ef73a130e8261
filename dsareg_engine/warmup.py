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


def warm_up_job(work_dir: Path, *, pose_search: bool = False) -> dict:
    """Load, register (``WARM_UP_ITERATIONS`` iterations), write every output and the DICOM results
    of a tiny phantom case in ``work_dir``, as a job does; returns the result dict. ``pose_search``:
    without an initial pose, so the pose search's kernels run too."""
    from .geometry.spec import parse_geometry
    from .io.case import CaseFiles
    from .pipeline import run_case

    work_dir = Path(work_dir)
    files = phantom_case_files(work_dir)
    if pose_search:
        geometry = json.loads(files["geometry"])
        geometry.pop("initial_mesh_to_world")
        files["geometry"] = json.dumps(geometry)
    case_files = CaseFiles(mesh=files["mesh"], mesh_name="mesh.obj", ap=files["ap"], ap_name="ap.png",
                           lat=files["lat"], lat_name="lat.png", geometry=parse_geometry(files["geometry"]))
    return run_case(case_files, {"starts": 1, "max_iterations": WARM_UP_ITERATIONS}, work_dir, label="warm-up",
                    dicom="required")


__all__ = ["WARM_UP_ITERATIONS", "WARM_UP_SIZE_PX", "phantom_case_files", "warm_up_job"]


def warm_up_renderer() -> None:
    """Load the pipeline and compile the renderer's kernels (both dtypes, forward and backward)."""
    import numpy as np
    import torch

    from . import pipeline  # noqa: F401 - loads the whole job path
    from .geometry.rig import ViewGeometry
    from .render import Camera, render_hard_silhouette, render_soft_silhouette

    view = ViewGeometry(image_size=(16, 16), pixel_spacing_mm=(1.0, 1.0), sid_mm=20.0,
                        principal_point_px=(7.5, 7.5), world_to_view=np.eye(4))
    faces = torch.tensor([[0, 1, 2]])
    for dtype in (torch.float32, torch.float64):  # Adam stages run in float32, the L-BFGS fit in float64
        vertices = torch.tensor([[-1.0, -1.0, 10.0], [1.0, -1.0, 10.0], [0.0, 1.0, 10.0]], dtype=dtype)
        pose = torch.eye(4, dtype=dtype)[None]
        render_hard_silhouette(vertices, faces, pose, Camera.from_view(view))
        render_soft_silhouette(vertices, faces, pose.requires_grad_(), Camera.from_view(view)).sum().backward()
    _warm_up_tracking(view, faces)


def _warm_up_tracking(view, faces) -> None:
    """Compile tracking's kernels (the silhouette Jacobian and the normal equations, float32)."""
    import numpy as np
    import torch

    from .render import Camera
    from .render.jacobian import jacobian_available, jacobian_kernel, soft_log_keep_tangents

    if not jacobian_available(torch.device("cpu")):
        return
    vertices = torch.tensor([[-1.0, -1.0, 10.0], [1.0, -1.0, 10.0], [0.0, 1.0, 10.0]], dtype=torch.float32)
    tangents = torch.zeros((1, 6, 4, 4), dtype=torch.float32)
    log_keep, log_keep_tangents = soft_log_keep_tangents(vertices, faces, torch.eye(4)[None], tangents, Camera.from_view(view))
    target = np.zeros((log_keep.shape[1], log_keep.shape[2] + 1), np.float32)[:, 1:]  # a window: not C-contiguous
    normal_equations, n_threads = jacobian_kernel("normal_equations")
    for weight in (np.zeros((0, 0), np.float32), target):
        normal_equations(log_keep[0], log_keep_tangents[0], target, weight, n_threads, np.zeros((6, 6)), np.zeros(6))
