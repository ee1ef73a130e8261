"""Two-view 3D/2D registration by silhouette matching.

Loss of one start: ``L = Σ_views λ_v · mean(w_v · (target_v − f(P_v | M))²)`` with ``f`` the
soft silhouette and ``P_v = world_to_view_v · mesh_to_world``: one rigid pose explains
both views. Stages run coarse to fine (see :mod:`.schedule`): Adam on all starts at low
resolution with soft edges and blurred targets (capture range), the best start refined
at finer levels, and L-BFGS at full resolution with a stop on pose change.

The parts, one module each: :mod:`.preparation` (inputs, starts, problem, stage list), :mod:`.stages` (the stage
runner), :mod:`.optimizers` (Adam, L-BFGS, Levenberg–Marquardt), :mod:`.starts` (the pose search's starts and
their bookkeeping), :mod:`.problem` (targets and the loss), :mod:`.level_of_detail` and :mod:`.summary` (the
result). Here: the entry point, the device and the mirror check around the whole registration.
"""

from __future__ import annotations

import contextlib
import time
from collections.abc import Callable

import numpy as np
import torch

from ..errors import DsaregInputError
from ..geometry.rig import Rig
from ..geometry.vessel_tree import select_region
from ..mesh import TriangleMesh
from ..render.jacobian import jacobian_available
from .mirror import with_mirror_check
from .options import RegistrationOptions
from .preparation import _prepare
from .progress import ProgressPlan
from .result import RegistrationResult
from .stages import ProgressCallback, RegistrationCanceled, _Reporter, _run_stages
from .summary import _summary

__all__ = ["ProgressCallback", "RegistrationCanceled", "register"]


@contextlib.contextmanager
def _torch_threads(count: int):
    """Run with ``count`` torch intra-op threads, restoring the previous setting afterwards.

    On the CPU the numba kernels carry the parallel work; the remaining torch operations
    are small, and torch's spinning OpenMP pool only competes with the kernels' threads.
    """
    previous = torch.get_num_threads()
    torch.set_num_threads(count)
    try:
        yield
    finally:
        torch.set_num_threads(previous)


def _resolve_device(requested: str, mode: str = "full") -> torch.device:
    """``auto``: CUDA when present, except for tracking, whose Levenberg–Marquardt steps run on the CPU
    kernels (measured on an H200 host pinned to 2 cores, paper mesh, 800 px: 254 ms per frame pair on
    the CPU against 454 ms with CUDA's Adam + L-BFGS)."""
    if requested == "auto" and mode == "track" and jacobian_available(torch.device("cpu")):
        return torch.device("cpu")
    if requested == "cuda" or (requested == "auto" and torch.cuda.is_available()):
        if not torch.cuda.is_available():
            raise DsaregInputError("CUDA was requested but no GPU is available", field="options.device", accepted="auto, cpu")
        return torch.device("cuda")
    return torch.device("cpu")


def register(
    mesh: TriangleMesh,
    masks: dict[str, np.ndarray],
    rig: Rig,
    options: RegistrationOptions | None = None,
    progress: ProgressCallback | None = None,
    should_stop: Callable[[], bool] | None = None,
    target_points: np.ndarray | None = None,
) -> RegistrationResult:
    """Estimate ``mesh_to_world`` so the mesh's silhouettes match the vessel masks.

    Args:
        mesh: vessel surface, mesh-frame mm.
        masks: ``{"ap": (H, W), "lat": (H, W)}``, each the size of its view: bool vessel masks, or
            float vessel coverage in [0, 1] per pixel (sub-pixel borders, e.g. from grey-level DSA,
            :func:`~dsareg_engine.vision.segmentation.vessel_coverage`), fitted as they are.
        rig: view geometry and the initial pose.
        options: see :class:`RegistrationOptions`.
        progress: called with ``{"stage", "iteration", "loss", "fraction"}`` every few iterations.
        should_stop: polled every iteration; True raises :class:`RegistrationCanceled`.
        target_points: ``(N, 3)`` mesh-frame points for mTRE (default: the vertices).

    Returns:
        :class:`RegistrationResult`.
    """
    options = options or RegistrationOptions()
    device = _resolve_device(options.device, options.mode)
    if options.region is not None:
        mesh = select_region(mesh, options.region)
    with _torch_threads(1 if device.type == "cpu" else torch.get_num_threads()):
        result = _register(mesh, masks, rig, options, device, progress, should_stop, target_points)
        return with_mirror_check(result, mesh, masks, rig, options, lambda mirror, masks_, rig_, options_: _register(
            mirror, masks_, rig_, options_, device, None, should_stop, None))


def _register(
    mesh: TriangleMesh,
    masks: dict[str, np.ndarray],
    rig: Rig,
    options: RegistrationOptions,
    device: torch.device,
    progress: ProgressCallback | None,
    should_stop: Callable[[], bool] | None,
    target_points: np.ndarray | None,
) -> RegistrationResult:
    setup = _prepare(mesh, masks, rig, options, device)
    reporter = _Reporter(ProgressPlan(setup.stages, len(setup.starts)), options, progress, should_stop)
    started = time.perf_counter()
    run = _run_stages(setup, options, reporter)
    return _summary(setup, run, options, time.perf_counter() - started, target_points)
