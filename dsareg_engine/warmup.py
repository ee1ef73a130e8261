"""Warm-up of a worker process: one tiny registration through every step a job takes.

A fresh process pays ~1.5 CPU-s on its first job for lazy imports and first-use set-up that
the renderer's warm-up does not reach: the loss
plot imports matplotlib and builds its font cache, the DICOM writer imports pydicom, the image
readers their codecs. Measured on 2 cores: first job 2.1 CPU-s, the next ones 0.5 CPU-s (128 px
phantom, 60 iterations; then, torch's optimizers also imported ``torch._dynamo``, which
:mod:`.registration.optim` no longer does). :func:`warm_up_job` pays this before the worker takes its first job.

The kernels (numba, cached on disk) are compiled in **groups** (:data:`KERNEL_GROUPS`), each group's
functions in one process so no two processes write one function's cache index at once:
``forward`` and ``backward`` are what a registration job needs (:func:`warm_up_kernels` compiles
``backward`` in a helper process while this one compiles ``forward``: two cores, half the wall time);
``tracking`` (the Gauss-Newton Jacobian, more than half of all the compile), ``search`` (the
initial-pose search), ``hemodynamics`` (the ray-stretch kernels of ``options.hemodynamics``) and ``volumes`` (a
volume reading's kernels: :mod:`.io.volume_kernels`) are compiled
afterwards by a background helper (:func:`compile_later_groups`),
so a worker is ready without them; a job that needs one before the helper is done compiles it itself.
``python -m dsareg_engine.warmup --threads N GROUP...`` is the helper.
"""

from __future__ import annotations

import io
import json
import os
import subprocess
import sys
import tempfile
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
    # no mirror fit: at this size two iterations leave a Dice below the mirror check's trigger even at the true pose,
    # and a first job that fits well does not fit the mirror (3.8 of the warm-up job's 5 CPU-s were that fit)
    return run_case(case_files, {"starts": 1, "max_iterations": WARM_UP_ITERATIONS, "mirror_check": False}, work_dir,
                    label="warm-up", dicom="required")


__all__ = ["KERNEL_GROUPS", "WARM_UP_ITERATIONS", "WARM_UP_SIZE_PX", "compile_later_groups", "phantom_case_files",
           "warm_up_job", "warm_up_kernels", "warm_up_renderer"]

JOB_GROUPS = ("forward", "backward")
LATER_GROUPS = ("tracking", "search", "hemodynamics", "volumes")
HELPER_WAIT_SECONDS = 600.0


def _tiny_view():
    import numpy as np

    from .geometry.rig import ViewGeometry

    return ViewGeometry(image_size=(16, 16), pixel_spacing_mm=(1.0, 1.0), sid_mm=20.0,
                        principal_point_px=(7.5, 7.5), world_to_view=np.eye(4))


def _tiny_triangle(dtype):
    import torch

    vertices = torch.tensor([[-1.0, -1.0, 10.0], [1.0, -1.0, 10.0], [0.0, 1.0, 10.0]], dtype=dtype)
    return vertices, torch.tensor([[0, 1, 2]]), torch.eye(4, dtype=dtype)[None]


def warm_up_renderer(*, tracking: bool = True) -> None:
    """Load the pipeline and compile (or load from the cache) the renderer's kernels, both dtypes, forward
    and backward; ``tracking``: tracking's kernels too."""
    import torch

    from . import pipeline  # noqa: F401 - loads the whole job path
    from .render import Camera, render_hard_silhouette, render_soft_silhouette

    camera = Camera.from_view(_tiny_view())
    for dtype in (torch.float32, torch.float64):  # Adam stages run in float32, the L-BFGS fit in float64
        vertices, faces, pose = _tiny_triangle(dtype)
        render_hard_silhouette(vertices, faces, pose, camera)
        render_soft_silhouette(vertices, faces, pose.requires_grad_(), camera).sum().backward()
    if tracking:
        _warm_up_tracking()


def _compile_forward() -> None:
    """The renderer's forward kernels and the gradient scatter (both dtypes), without the backward kernel."""
    import numpy as np
    import torch

    from .render import Camera, render_hard_silhouette, render_soft_silhouette
    from .render.silhouette import _kernel

    camera = Camera.from_view(_tiny_view())
    for dtype in (torch.float32, torch.float64):
        vertices, faces, pose = _tiny_triangle(dtype)
        render_hard_silhouette(vertices, faces, pose, camera)
        render_soft_silhouette(vertices, faces, pose, camera)
        grad_triangles = np.zeros((1, 1, 3, 2), vertices.numpy().dtype)  # as _SoftLogKeepNumba.backward passes them
        _kernel("scatter_to_vertices")[0](grad_triangles, faces.numpy(), np.zeros((1, 3, 2), grad_triangles.dtype))


def _compile_backward() -> None:
    """The renderer's backward kernel, both dtypes, with the argument types _SoftLogKeepNumba.backward passes."""
    import numpy as np

    from .render.silhouette import _SIGMOID_TABLE, _kernel

    for dtype in (np.float32, np.float64):
        triangles = np.zeros((1, 1, 3, 2), dtype)
        boxes = np.array([[[1, 0, 1, 0]]], np.int32)  # an empty box: nothing to do, only the compile
        kernel, n_threads = _kernel("soft_log_keep_backward")
        kernel(triangles, boxes, 1.0, 1.0, dtype == np.float64, _SIGMOID_TABLE, n_threads, np.zeros((1, 2, 2), dtype),
               np.zeros_like(triangles))


def _compile_search() -> None:
    """The pose search's kernels, through a tiny job without an initial pose (their real argument types), and the
    coverage search's splat (which that job's fully visible phantom does not reach), with its argument types."""
    import numba
    import numpy as np

    from .registration.search.coverage_search import _SPLAT

    with tempfile.TemporaryDirectory(prefix="dsareg-warm-up-search-") as work_dir:
        warm_up_job(Path(work_dir), pose_search=True)
    points, turns = np.zeros((1, 3)), np.eye(3)[None].copy()
    offsets, intrinsics = np.array([[0.0, 0.0, 10.0]]), np.array([1.0, 1.0, 0.0, 0.0])
    _SPLAT.pick(numba.get_num_threads())(points, turns, offsets, intrinsics, 0, np.zeros((1, 4, 4), np.float32))


def _warm_up_tracking() -> None:
    """Compile tracking's kernels (the silhouette Jacobian and the normal equations, float32)."""
    import numpy as np
    import torch

    from .render import Camera
    from .render.jacobian import jacobian_available, jacobian_kernel, soft_log_keep_tangents

    if not jacobian_available(torch.device("cpu")):
        return
    view = _tiny_view()
    faces = torch.tensor([[0, 1, 2]])
    vertices = torch.tensor([[-1.0, -1.0, 10.0], [1.0, -1.0, 10.0], [0.0, 1.0, 10.0]], dtype=torch.float32)
    tangents = torch.zeros((1, 6, 4, 4), dtype=torch.float32)
    log_keep, log_keep_tangents = soft_log_keep_tangents(vertices, faces, torch.eye(4)[None], tangents, Camera.from_view(view))
    target = np.zeros((log_keep.shape[1], log_keep.shape[2] + 1), np.float32)[:, 1:]  # a window: not C-contiguous
    normal_equations, n_threads = jacobian_kernel("normal_equations")
    for weight in (np.zeros((0, 0), np.float32), target):
        normal_equations(log_keep[0], log_keep_tangents[0], target, weight, n_threads, np.zeros((6, 6)), np.zeros(6))


def _compile_hemodynamics() -> None:
    """The ray-stretch kernels hemodynamics traces the model with (and the bolus simulation), with a job's argument
    types: a tetrahedron in front of a tiny view."""
    import numpy as np

    from .render.ray_layers import ray_stretches

    vertices = np.array([[0.0, 0.0, 10.0], [1.0, 0.0, 10.0], [0.0, 1.0, 10.0], [0.0, 0.0, 11.0]])
    faces = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
    ray_stretches(vertices, faces, (8.0, 8.0), (3.5, 3.5), (8, 8))


def _compile_volumes() -> None:
    """The kernels of a volume reading, with the argument types it passes: the distance transform of its wide bands
    (:func:`.io.voxel_band.within_mm`: a C-ordered bool grid, three spacings, a float64 grid), the smoothing
    (:func:`.io.smoothing_kernels.compile_smoothing_kernels`), the plate search's kernels
    (:func:`.io.medial_kernels.compile_medial_kernels`), the labelling by runs
    (:func:`.io.label_kernels.compile_label_kernels`) and the whole-box steps
    (:func:`.io.voxel_kernels.compile_voxel_kernels`)."""
    import numpy as np

    from .io.distance_kernels import squared_distances
    from .io.label_kernels import compile_label_kernels
    from .io.medial_kernels import compile_medial_kernels
    from .io.smoothing_kernels import compile_smoothing_kernels
    from .io.voxel_kernels import compile_voxel_kernels

    squared_distances(np.ones((2, 2, 2), bool), 1.0, 1.0, 1.0, np.empty((2, 2, 2)))
    compile_smoothing_kernels()
    compile_medial_kernels()
    compile_label_kernels()
    compile_voxel_kernels()


KERNEL_GROUPS = {"forward": _compile_forward, "backward": _compile_backward, "tracking": _warm_up_tracking,
                 "search": _compile_search, "hemodynamics": _compile_hemodynamics, "volumes": _compile_volumes}
"""Kernel groups: name → the function that compiles them (each group's numba functions belong to it alone)."""


def _group_dispatchers(name: str) -> list:
    """The numba dispatchers a group compiles, for this process's thread budget (serial twins on 1 thread)."""
    from .render.jacobian import jacobian_kernel
    from .render.silhouette import _kernel

    if name == "forward":
        return [_kernel(k)[0] for k in ("gather_faces", "soft_log_keep", "coverage", "scatter_to_vertices")]
    if name == "backward":
        return [_kernel("soft_log_keep_backward")[0]]
    if name == "hemodynamics":
        from .render.ray_layers import _hits, _pair

        return [_hits, _pair]
    if name == "volumes":
        from .io.distance_kernels import squared_distances
        from .io.label_kernels import LABEL_KERNELS
        from .io.medial_kernels import MEDIAL_KERNELS
        from .io.smoothing_kernels import KERNELS
        from .io.voxel_kernels import VOXEL_KERNELS

        return [squared_distances, *MEDIAL_KERNELS, *LABEL_KERNELS, *VOXEL_KERNELS, *KERNELS]
    if name == "tracking":
        from .render import jacobian_numba

        return [jacobian_kernel("soft_log_keep_tangents")[0], jacobian_kernel("normal_equations")[0],
                jacobian_numba.gather_faces_with_tangents]
    from .registration.search.coverage_search import _SPLAT
    from .registration.search.initialization import _SEARCH_KERNELS
    from numba import get_num_threads

    return [pair.pick(get_num_threads()) for pair in (*_SEARCH_KERNELS.values(), _SPLAT)]


def group_cached(name: str) -> bool:
    """Whether every kernel of the group has a compiled version in numba's on-disk cache (for these sources;
    an entry for another CPU counts too: the worker then compiles that kernel itself)."""
    try:
        return all(len(d._cache._cache_file._load_index()) > 0 for d in _group_dispatchers(name))
    except Exception:  # noqa: BLE001 - numba's cache internals moved: assume not cached
        return False


def compile_group(name: str) -> None:
    """Compile the kernel group ``name`` into the cache (under its lock, see :mod:`.kernels.compile_lock`)."""
    from .kernels.compile_lock import compiling_group

    with compiling_group(name):
        KERNEL_GROUPS[name]()


def start_helper(groups: list[str], *, background: bool = False) -> subprocess.Popen | None:
    """A helper process compiling ``groups`` into the cache for this process's thread budget; None when they are
    all cached already. It dies with this process; ``background``: at the lowest CPU priority."""
    import numba

    missing = [g for g in groups if not group_cached(g)]
    if not missing:
        return None
    command = [sys.executable, "-m", "dsareg_engine.warmup", "--threads", str(numba.get_num_threads()),
               *(["--background"] if background else []), *missing]
    return subprocess.Popen(command, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL if background else subprocess.PIPE,
                            env={**os.environ, "DSAREG_PARENT_PID": str(os.getpid())})


def warm_up_kernels() -> None:
    """The kernels a registration job needs, compiled (or loaded) into this process: ``backward`` in a helper
    process while this one compiles ``forward``; then both load from the cache."""
    helper = start_helper(["backward"])
    compile_group("forward")
    if helper is not None:
        try:
            _, errors = helper.communicate(timeout=HELPER_WAIT_SECONDS)
        except subprocess.TimeoutExpired:
            helper.kill()
            errors = b"timed out"
        if helper.returncode:  # not fatal: this process compiles what is missing
            print(f"kernel helper failed ({helper.returncode}): {errors.decode(errors='replace')[-500:]}", file=sys.stderr)
    warm_up_renderer(tracking=False)  # the backward kernel loads from the cache (or compiles here if the helper failed)


def compile_later_groups() -> subprocess.Popen | None:
    """Start the background helper that compiles the kernels no first job needs (tracking, pose search,
    hemodynamics)."""
    return start_helper(list(LATER_GROUPS), background=True)


def _die_with_parent() -> None:
    """Linux: SIGKILL this helper when the process that started it dies (no orphaned compiles)."""
    parent = os.environ.get("DSAREG_PARENT_PID")
    if not parent or not sys.platform.startswith("linux"):
        return
    import ctypes
    import signal

    ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG
    if os.getppid() != int(parent):  # the parent died before the prctl
        os._exit(1)


def main(argv: list[str] | None = None) -> int:
    """``python -m dsareg_engine.warmup [--threads N] [--background] GROUP...``: compile kernel groups."""
    import argparse

    parser = argparse.ArgumentParser(prog="python -m dsareg_engine.warmup", description=main.__doc__)
    parser.add_argument("groups", nargs="+", choices=list(KERNEL_GROUPS))
    parser.add_argument("--threads", type=int, default=1, help="the thread budget to compile for (serial twins on 1)")
    parser.add_argument("--background", action="store_true", help="at the lowest CPU priority")
    args = parser.parse_args(argv)
    _die_with_parent()
    from .commands.process_exit import skip_exit_collections

    skip_exit_collections()
    if args.background:
        os.nice(19)
    from .threads import set_cpu_threads

    set_cpu_threads(args.threads)
    for name in args.groups:
        compile_group(name)
    return 0


if __name__ == "__main__":  # through the imported module, so KERNEL_GROUPS and its imports are the ones the kernels see
    from dsareg_engine.warmup import main as _main

    sys.exit(_main())
