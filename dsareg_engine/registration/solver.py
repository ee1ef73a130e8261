"""Two-view 3D/2D registration by silhouette matching.

Loss of one start: ``L = Σ_views λ_v · mean(w_v · (target_v − f(P_v | M))²)`` with ``f`` the
soft silhouette and ``P_v = world_to_view_v · mesh_to_world``: one rigid pose explains
both views. Stages run coarse to fine (see :mod:`.schedule`): Adam on all starts at low
resolution with soft edges and blurred targets (capture range), the best start refined
at finer levels, and L-BFGS at full resolution with a stop on pose change.
"""

from __future__ import annotations

import contextlib
import hashlib
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import torch

from ..errors import DsaregInputError
from ..geometry.rig import Rig
from ..mesh import TriangleMesh, decimate
from ..metrics import dice, ground_truth_errors, iou, mean_distance_mm
from ..geometry.pose import validate_rigid
from ..render import Camera, SilhouetteSettings, render_hard_silhouette, render_soft_silhouette
from ..render.jacobian import jacobian_available
from ..vision.vessel_target import binary_mask, is_coverage
from ..geometry.vessel_tree import compact, select_region
from .border import update_border_shift
from .confidence import ConfidenceThresholds, assess, outside_fraction, runner_up, tolerant_f_score
from .gauss_newton import levenberg_marquardt
from .search.branch_search import with_branch_starts
from .search.initialization import GIVEN_INITIALIZATION, Initialization, resolve_initialization, search_initial_poses
from .mirror import with_mirror_check
from .options import RegistrationOptions
from .partial import explained_faces, looks_partial, match_fractions, refit_faces, trimmed_weight
from .parameterization import PoseIncrement, mesh_radius_mm, random_start_poses
from .progress import ProgressPlan
from .result import RegistrationResult, ViewResult
from .schedule import COARSEST_SIDE_PX, WINDOW_TOLERANCE, Stage, build_schedule
from .targets import ViewTarget, gaussian_blur, level_target, shifted_mask, signed_border_distance
from .track import build_track_schedule, motion_between

ProgressCallback = Callable[[dict], None]

AGREEMENT_ADD_MM = 2.0
"""Starts whose pose lies within this ADD of the best one after the batched stages agree."""
SEARCH_MIN_STARTS = 8
"""A pose search hands at least this many distinct starts to the solver (measured on grey-level
phantom cases with no initial pose: 4 starts 60 %, 8 starts 80 %, 12 starts 80 % success)."""
MIN_COARSE_OBJECT_PX = 48
"""After a pose search, pyramid levels where the vessels span fewer pixels than this are skipped."""
DISTINCT_RADIUS_FRACTION = 0.2
"""A start is a distinct solution (confidence's runner-up) beyond this fraction of the mesh's RMS radius
(and beyond AGREEMENT_ADD_MM): nearer ones are the same answer, not yet refined."""
ADAM_PATIENCE = 8
LBFGS_POSE_TOLERANCE = 1e-4
"""L-BFGS stops when a step changes every pose component by less than this (mm units)."""
WINDOW_MARGIN_PX = 12.0
"""Room (px of the stage's image) left around the mesh's footprint when a stage's loss is windowed."""
BORDER_RECHECK_PX = 0.2
"""A refinement whose end pose moves a view's measured border shift by more than this (px) runs once more."""
MIN_CONVERGED_DICE = 0.5
LOD_MIN_FACES = 1500
LOD_FACE_AREA_PX = 2.0
LOD_STEPS_PER_DOUBLING = 8


def level_of_detail_faces(n_faces: int, mean_face_area_px: float) -> int:
    """Faces to keep so the mean projected face covers about ``LOD_FACE_AREA_PX`` px² (≥ LOD_MIN_FACES).

    Rounded to steps of 2^(1/8) (~9 %) above LOD_MIN_FACES, so registrations of one mesh at nearby
    poses (tracking: every frame) ask for the same level of detail and find it remembered (measured:
    2845, 2888 and 2896 faces on three consecutive frames, each a ~15 ms decimation).
    """
    wanted = max(LOD_MIN_FACES, n_faces * mean_face_area_px / LOD_FACE_AREA_PX)
    steps = round(LOD_STEPS_PER_DOUBLING * math.log2(wanted / LOD_MIN_FACES))
    return int(min(n_faces, round(LOD_MIN_FACES * 2 ** (steps / LOD_STEPS_PER_DOUBLING))))


def mean_projected_face_area_px(mesh: TriangleMesh, view, mesh_to_world: np.ndarray) -> float:
    """Mean area (px², full resolution) of the mesh's faces projected into ``view``."""
    pixels = view.project(mesh.vertices @ mesh_to_world[:3, :3].T + mesh_to_world[:3, 3])
    a, b, c = (pixels[mesh.faces[:, k]] for k in range(3))
    e1, e2 = b - a, c - a
    return float(np.abs(e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]).mean() / 2.0)


_LOD_CACHE: dict[tuple[str, int], TriangleMesh] = {}
_LOD_CACHE_SIZE = 8


def _decimated(mesh: TriangleMesh, faces: int) -> TriangleMesh:
    """``decimate(mesh, faces)``, remembered across registrations of the same mesh (tracking
    re-registers one model frame after frame; decimation cost ~35 ms per level of detail)."""
    digest = hashlib.sha1(np.ascontiguousarray(mesh.vertices).tobytes() + np.ascontiguousarray(mesh.faces).tobytes()).hexdigest()
    key = (digest, faces)
    if key not in _LOD_CACHE:
        if len(_LOD_CACHE) >= _LOD_CACHE_SIZE:
            _LOD_CACHE.pop(next(iter(_LOD_CACHE)))
        _LOD_CACHE[key] = decimate(mesh, faces)
    return _LOD_CACHE[key]


class RegistrationCanceled(Exception):
    """Raised when ``should_stop()`` returned True between iterations."""


@dataclass
class _StageOutcome:
    iterations: int
    seconds: float
    stopped_by: str  # "tolerance" | "iterations"
    losses: list[float]
    final_loss: float | None = None
    """The one start's loss at the end, when the runner knows it (Gauss–Newton); else it is re-evaluated."""


class _Problem:
    """The mesh, the rig and the per-level targets, shared by all stages."""

    def __init__(
        self, mesh: TriangleMesh, masks: dict[str, np.ndarray], rig: Rig, options: RegistrationOptions,
        device: torch.device, initial_mesh_to_world: np.ndarray,
    ):
        self.mesh = mesh
        self.targets = masks
        """Per view what the loss fits: a mask (bool) or a vessel coverage map (float in [0, 1])."""
        self.masks = {name: binary_mask(target) for name, target in masks.items()}
        """Per view the binary mask (Dice, fit scores)."""
        self.rig = rig
        self.options = options
        self.device = device
        self.centre = mesh.centroid
        self.radius_mm = mesh_radius_mm(mesh.vertices)
        self.mean_face_area_px = min(
            mean_projected_face_area_px(mesh, view, initial_mesh_to_world) for view in rig.views.values()
        )
        self._targets: dict[tuple, ViewTarget] = {}
        self.border_shift_px = {name: 0.0 for name in masks}
        self._signed_distance: dict[str, np.ndarray] = {}
        self._mesh_tensors: dict[tuple, tuple[torch.Tensor, torch.Tensor]] = {}
        self.windows: dict[tuple[str, float], tuple[int, int, int, int]] = {}
        """Per (view, scale): the pixel window ``(x0, y0, x1, y1)`` the loss is evaluated in (see set_windows)."""
        self.partial = False
        """Partial visibility (see :mod:`.partial`): background far from the vessels weighs little in the loss."""
        self.fit_mesh = mesh
        """What the loss renders: the mesh, or the part of it the branch search matched to the images
        (:mod:`.branch_search`); the pose, the signals and the views are always the whole mesh's."""
        self.fit_faces: np.ndarray | None = None
        """``(F,)`` bool: the faces of :attr:`fit_mesh` in the mesh, when it is a part."""

    def fit_part(self, faces: np.ndarray) -> None:
        """Render the part ``faces`` ``(F,)`` bool of the mesh in the loss from now on."""
        self.fit_faces, self.fit_mesh = faces, compact(self.mesh, faces)
        self._mesh_tensors.clear()

    def _footprint(self, view, poses: np.ndarray) -> np.ndarray:
        """Pixel bounding box ``(u_min, v_min, u_max, v_max)`` of the mesh's vertices under all ``poses`` in ``view``."""
        vertices = self.mesh.vertices
        projected = np.concatenate([view.project(vertices @ pose[:3, :3].T + pose[:3, 3]) for pose in poses])
        return np.concatenate([projected.min(axis=0), projected.max(axis=0)])

    def set_windows(self, stage: Stage, poses: np.ndarray, dtype: torch.dtype) -> None:
        """Restrict the stage's loss to the box around the target and the mesh at ``poses`` (plus a margin).

        Outside the target's support (the mask, widened by the blur) and the silhouettes' support
        (the projected mesh, widened by the edge cutoff) both images are exactly 0, so the sum of
        squared errors over the window equals the one over the whole image; on the paper's mesh
        the window is about half the image, and rendering, shading and the loss skip the rest.
        The margin leaves room for the stage's own motion; :meth:`windows_hold` checks it after.
        """
        for name in stage.views:
            target = self.target(name, stage, dtype)
            height, width = target.target.shape
            support = torch.nonzero(target.target.sum(dim=0) > 0).flatten(), torch.nonzero(target.target.sum(dim=1) > 0).flatten()
            if len(support[0]) == 0:
                self.windows.pop((name, stage.scale), None)
                continue
            box = self._footprint(target.view, poses)
            pad = WINDOW_MARGIN_PX + SilhouetteSettings(sigma_px=stage.sigma_px).blur_radius_px + 3.0 * stage.blur_px
            x0 = int(max(0, min(support[0][0].item(), np.floor(box[0] - pad))))
            y0 = int(max(0, min(support[1][0].item(), np.floor(box[1] - pad))))
            x1 = int(min(width, max(support[0][-1].item() + 1, np.ceil(box[2] + pad) + 1)))
            y1 = int(min(height, max(support[1][-1].item() + 1, np.ceil(box[3] + pad) + 1)))
            self.windows[(name, stage.scale)] = (x0, y0, x1, y1)

    def windows_hold(self, stage: Stage, poses: np.ndarray, dtype: torch.dtype) -> bool:
        """True when the mesh at ``poses`` still projects inside every window of the stage, with its edge cutoff."""
        for name in stage.views:
            window = self.windows.get((name, stage.scale))
            if window is None:
                continue
            box = self._footprint(self.target(name, stage, dtype).view, poses)
            pad = SilhouetteSettings(sigma_px=stage.sigma_px).blur_radius_px + 3.0 * stage.blur_px + 1.0
            x0, y0, x1, y1 = window
            height, width = self.target(name, stage, dtype).target.shape
            if ((x0 > 0 and box[0] - pad < x0) or (y0 > 0 and box[1] - pad < y0)
                    or (x1 < width and box[2] + pad > x1 - 1) or (y1 < height and box[3] + pad > y1 - 1)):
                return False
        return True

    def mesh_tensors(self, dtype: torch.dtype, stage: Stage | None = None, fit: bool = False) -> tuple[torch.Tensor, torch.Tensor]:
        """Vertices and faces for rendering a stage (or with ``fit``: the fitted part, :attr:`fit_mesh`; else the
        whole mesh): a decimated level of detail for Adam stages.

        Faces much smaller than a pixel cost a whole blur disc each and make the soft
        silhouette swell; decimating to about ``LOD_FACE_AREA_PX`` px² per face (as projected
        at the stage's scale) keeps cost and swelling in check. The final L-BFGS stage
        always uses the full mesh so accuracy does not depend on the decimation.
        """
        source = self.fit_mesh if stage is not None or fit else self.mesh
        faces_wanted = source.n_faces
        if stage is not None and (stage.optimizer == "adam" if stage.level_of_detail is None else stage.level_of_detail):
            faces_wanted = level_of_detail_faces(source.n_faces, self.mean_face_area_px * stage.scale**2)
        key = (dtype, faces_wanted, source is self.mesh)
        if key not in self._mesh_tensors:
            mesh = source if faces_wanted >= source.n_faces else _decimated(source, faces_wanted)
            self._mesh_tensors[key] = mesh.torch(dtype, self.device)
        return self._mesh_tensors[key]

    def target(self, view_name: str, stage: Stage, dtype: torch.dtype) -> ViewTarget:
        shift = self.border_shift_px[view_name]
        key = (view_name, stage.scale, stage.blur_px, dtype, shift, self.partial)
        if key not in self._targets:
            target = level_target(
                self.targets[view_name], self.rig.views[view_name], stage.scale, stage.blur_px,
                self.options.thin_vessel_weighting, dtype, shift, self.signed_distance(view_name) if shift else None,
            )
            if self.partial:
                trimmed = torch.as_tensor(trimmed_weight(target.target.numpy()), dtype=dtype)
                target.weight = trimmed if target.weight is None else target.weight * trimmed
            target.target = target.target.to(self.device)
            if target.weight is not None:
                target.weight = target.weight.to(self.device)
            self._targets[key] = target
        return self._targets[key]

    def signed_distance(self, view_name: str) -> np.ndarray:
        """The view's target as a signed border distance (px, sub-pixel for a coverage map), computed once."""
        if view_name not in self._signed_distance:
            self._signed_distance[view_name] = signed_border_distance(self.targets[view_name])
        return self._signed_distance[view_name]

    def update_border_shifts(self, mesh_to_world: np.ndarray, views: tuple[str, ...]) -> None:
        """Re-measure each view's target border shift against the fitted mesh at ``mesh_to_world``."""
        vertices, faces = self.mesh_tensors(torch.float64, fit=True)
        for name in views:
            view = self.rig.views[name]
            pose = torch.as_tensor(view.world_to_view @ mesh_to_world, device=self.device)[None]
            silhouette = render_hard_silhouette(vertices, faces, pose, Camera.from_view(view))[0].cpu().numpy()
            self.border_shift_px[name] = update_border_shift(
                self.targets[name], silhouette, self.border_shift_px[name], self.signed_distance(name))

    def match_fractions(self, mesh_to_world: np.ndarray, views: tuple[str, ...]) -> dict[str, dict]:
        """Per view the unmatched / uncovered fractions (:func:`.partial.match_fractions`) of the full mesh at ``mesh_to_world``."""
        vertices, faces = self.mesh_tensors(torch.float64)
        fractions = {}
        for name in views:
            view = self.rig.views[name]
            pose = torch.as_tensor(view.world_to_view @ mesh_to_world, device=self.device)[None]
            silhouette = render_hard_silhouette(vertices, faces, pose, Camera.from_view(view))[0].cpu().numpy()
            fractions[name] = match_fractions(silhouette, self.masks[name])
        return fractions

    def view_inputs(self, name: str, stage: Stage, dtype: torch.dtype) -> tuple[Camera, torch.Tensor, torch.Tensor | None, int]:
        """The stage's camera, target ``(h, w)`` and weight ``(h, w)`` or None, cut to its window if it has
        one, and the pixel count of the whole level image (the loss is a mean over it)."""
        target = self.target(name, stage, dtype)
        camera, image, weight = target.camera, target.target, target.weight
        pixels = image.numel()
        window = self.windows.get((name, stage.scale))
        if window is not None:
            x0, y0, x1, y1 = window
            camera = Camera(camera.focal_px, (camera.principal_point_px[0] - x0, camera.principal_point_px[1] - y0),
                            x1 - x0, y1 - y0)
            image = image[y0:y1, x0:x1]
            weight = None if weight is None else weight[y0:y1, x0:x1]
        return camera, image, weight, pixels

    def loss(self, mesh_to_world: torch.Tensor, stage: Stage, dtype: torch.dtype) -> torch.Tensor:
        """Per-start loss ``(B,)`` for poses ``(B, 4, 4)`` (float64, differentiable)."""
        vertices, faces = self.mesh_tensors(dtype, stage)
        settings = SilhouetteSettings(sigma_px=stage.sigma_px)
        total = torch.zeros(mesh_to_world.shape[0], dtype=dtype, device=self.device)
        for name in stage.views:
            target = self.target(name, stage, dtype)
            world_to_view = torch.as_tensor(self.rig.views[name].world_to_view, dtype=torch.float64)
            mesh_to_view = (world_to_view @ mesh_to_world).to(dtype=dtype, device=self.device)
            camera, image, weight, pixels = self.view_inputs(name, stage, dtype)
            alpha = gaussian_blur(render_soft_silhouette(vertices, faces, mesh_to_view, camera, settings), target.blur_px)
            error = (alpha - image) ** 2
            if weight is not None:
                error = error * weight
            total = total + error.sum(dim=(1, 2)) / pixels
        return total


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


def _run_adam(problem, stage, increment, delta, dtype, report) -> _StageOutcome:
    optimizer = torch.optim.Adam([delta], lr=stage.learning_rate)
    losses: list[float] = []
    best, since_best = float("inf"), 0
    start = time.perf_counter()
    stopped_by = "iterations"
    iteration = 0
    for iteration in range(1, stage.max_iterations + 1):
        optimizer.zero_grad()
        per_start = problem.loss(increment(delta), stage, dtype)
        per_start.sum().backward()
        optimizer.step()
        value = float(per_start.detach().min())
        losses.append(value)
        report(stage, iteration, value)
        if stage.plateau_window:
            if _window_plateau(losses, stage.plateau_window):
                stopped_by = "tolerance"
                break
        elif value < best * (1.0 - stage.plateau_tolerance):
            best, since_best = value, 0
        else:
            since_best += 1
            if since_best >= ADAM_PATIENCE:
                stopped_by = "tolerance"
                break
    return _StageOutcome(iteration, time.perf_counter() - start, stopped_by, losses)


def _window_plateau(losses: list[float], window: int) -> bool:
    """True when the mean of the last ``window`` losses is less than WINDOW_TOLERANCE below the mean of the window before."""
    if len(losses) < 2 * window:
        return False
    last, before = np.mean(losses[-window:]), np.mean(losses[-2 * window:-window])
    return bool(last > before * (1.0 - WINDOW_TOLERANCE))


def _run_lbfgs(problem, stage, increment, delta, dtype, report) -> _StageOutcome:
    optimizer = torch.optim.LBFGS(
        [delta], lr=1.0, max_iter=stage.max_iterations, max_eval=stage.max_iterations,
        tolerance_grad=1e-12, tolerance_change=LBFGS_POSE_TOLERANCE if stage.pose_tolerance is None else stage.pose_tolerance,
        history_size=10, line_search_fn="strong_wolfe",
    )
    losses: list[float] = []
    start = time.perf_counter()
    # L-BFGS compares its tolerance with loss and slope values: use the sum of squared
    # errors (the per-pixel mean times the pixel count) so they are of order one.
    first = problem.target(stage.views[0], stage, dtype).target
    pixels = float(first.numel())

    def closure():
        optimizer.zero_grad()
        mean_loss = problem.loss(increment(delta), stage, dtype).sum()
        (mean_loss * pixels).backward()
        losses.append(float(mean_loss.detach()))
        report(stage, len(losses), losses[-1])
        return mean_loss.detach() * pixels

    optimizer.step(closure)
    evaluations = len(losses)
    stopped_by = "iterations" if evaluations >= stage.max_iterations else "tolerance"
    return _StageOutcome(evaluations, time.perf_counter() - start, stopped_by, losses)


def _run_gauss_newton(problem, stage, increment, delta, dtype, report) -> _StageOutcome:
    start = time.perf_counter()
    pose = increment.poses(delta.detach())[0]
    tolerance = LBFGS_POSE_TOLERANCE if stage.pose_tolerance is None else stage.pose_tolerance
    pose, final_loss, losses, converged = levenberg_marquardt(
        problem, stage, pose, dtype, tolerance, lambda iteration, loss: report(stage, iteration, loss))
    with torch.no_grad():
        delta.copy_(torch.as_tensor(increment.delta_of(pose[None])))
    return _StageOutcome(len(losses), time.perf_counter() - start, "tolerance" if converged else "iterations", losses,
                         final_loss)


_RUNNERS = {"adam": _run_adam, "lbfgs": _run_lbfgs, "gauss_newton": _run_gauss_newton}


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


@dataclass
class _Run:
    """The stage runner's state, carried from stage to stage: the live starts and the kept start's history."""

    poses: np.ndarray
    pose_history: list[np.ndarray]
    frames: list[tuple[str, int, np.ndarray]]
    iterations: dict[str, int] = field(default_factory=dict)
    seconds: dict[str, float] = field(default_factory=dict)
    loss_history: list[tuple[str, list[float]]] = field(default_factory=list)
    starts_agreeing: int = 1
    other: dict | None = None
    """Confidence's runner-up (see :func:`_runner_up`), measured when the batched stages hand over."""
    outcome: _StageOutcome | None = None
    final_loss: float = float("nan")
    partial_checked: bool = False


class _Reporter:
    """The runners' per-iteration callback: cancellation, animation snapshots and progress events.

    :meth:`begin` names the stage and the increment/delta being optimized before a runner starts,
    so every name the callback reads is set before it is called.
    """

    def __init__(self, plan: ProgressPlan, options: RegistrationOptions, progress: ProgressCallback | None,
                 should_stop: Callable[[], bool] | None):
        self.plan, self.options, self.progress, self.should_stop = plan, options, progress, should_stop
        self.stage_index = 0
        self.snapshots: list[tuple[int, np.ndarray]] = []
        self.increment: PoseIncrement | None = None
        self.delta: torch.Tensor | None = None

    def begin(self, stage_index: int, increment: PoseIncrement, delta: torch.Tensor) -> None:
        self.stage_index, self.increment, self.delta, self.snapshots = stage_index, increment, delta, []

    def __call__(self, stage: Stage, iteration: int, loss: float) -> None:
        if self.should_stop is not None and self.should_stop():
            raise RegistrationCanceled("registration canceled")
        if self.options.animation:  # every start's pose at this iteration, for the animation
            self.snapshots.append((iteration, self.increment.poses(self.delta.detach())))
        if self.progress is not None and (iteration % 5 == 0 or iteration == 1):
            fraction = self.plan.fraction(self.stage_index, iteration)
            self.progress({"stage": stage.name, "iteration": iteration, "loss": loss, "fraction": fraction})


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
    problem.partial = searched is not None and searched.method.startswith("search+")
    if searched is not None and searched.fit_faces is not None:
        problem.fit_part(searched.fit_faces)
    longest = max(max(rig.views[name].image_size) for name in used_views)
    final_scale = min(1.0, options.working_size_px / longest) if options.working_size_px else 1.0
    shortest = min(min(rig.views[name].image_size) for name in used_views)
    tracking = options.mode == "track"
    side_px = round(shortest * final_scale)
    schedule = (
        build_track_schedule(used_views, side_px, options.max_iterations, jacobian_available(device)) if tracking
        else _ladder_schedule(options, side_px, masks, used_views, final_scale)
    )
    stages = [Stage(**{**vars(stage), "scale": stage.scale * final_scale}) for stage in schedule]
    starts = searched.poses if searched is not None else random_start_poses(
        initial, problem.centre, 1 if tracking else options.starts, options.start_spread_deg, options.start_spread_mm,
        options.seed)
    return _Setup(problem, used_views, initial, searched, stages, starts, tracking)


def _ladder_schedule(options: RegistrationOptions, side_px: int, masks: dict[str, np.ndarray], used_views,
                     final_scale: float) -> list[Stage]:
    """The coarse-to-fine stages: the image's pyramid, its coarsest level set by the vessels' extent when that is
    what limits it (:func:`_coarsest_scale`), else by :func:`_pyramid_side_px`'s power-of-two rule."""
    coarsest = _coarsest_scale(side_px, masks, used_views, final_scale)
    side = side_px if coarsest is not None else _pyramid_side_px(side_px, masks, used_views, final_scale)
    return build_schedule(options.configuration, side, options.max_iterations, options.coarse_to_fine, options.refine,
                          coarsest)


def _run_stages(setup: _Setup, options: RegistrationOptions, reporter: _Reporter) -> _Run:
    """Run the stage list in order; then, when the final border re-measurement moved (see
    :func:`_border_moved`), the final stage once more as ``<name>:again``."""
    run = _Run(poses=setup.starts, pose_history=[setup.starts[0]], frames=[("initial", 0, setup.initial)])
    finest_scale = max(stage.scale for stage in setup.stages)
    for index, stage in enumerate(setup.stages):
        _run_stage(setup, run, reporter, options, index, stage, finest_scale)
    last = setup.stages[-1]
    if not setup.tracking and _border_moved(setup.problem, options, last, setup.used_views, run.poses[0]):
        again = Stage(**{**vars(last), "name": f"{last.name}:again"})
        _run_stage(setup, run, reporter, options, len(setup.stages), again, finest_scale)
    if _refit_explained(setup.problem, run.poses[0], setup.used_views):
        explained = Stage(**{**vars(last), "name": f"{last.name}:explained"})
        _run_stage(setup, run, reporter, options, len(setup.stages), explained, finest_scale)
    return run


def _refit_explained(problem: _Problem, pose: np.ndarray, used_views) -> bool:
    """After a part was fitted: when the part holds faces the images do not show at ``pose``, fit the faces they
    do show from now on (:func:`.partial.refit_faces`) and return True."""
    if problem.fit_faces is None:
        return False
    explained = explained_faces(problem.mesh, pose, {name: problem.masks[name] for name in used_views}, problem.rig)
    faces = refit_faces(problem.fit_faces, explained)
    if faces is None:
        return False
    problem.fit_part(faces)
    return True


def _run_stage(setup: _Setup, run: _Run, reporter: _Reporter, options: RegistrationOptions, index: int, stage: Stage,
               finest_scale: float) -> None:
    """One stage on ``run.poses``: border update, start pruning, windowing, the optimizer, bookkeeping.
    ``index`` is the stage's place in ``setup.stages`` (``len(setup.stages)`` for the extra final run)."""
    problem, planned = setup.problem, len(setup.stages)
    problem.windows.clear()
    if stage.add_initial_starts:
        run.poses = np.concatenate([run.poses, setup.starts])
    # Fine stages only, and not in the single-view phase of a sequential configuration: one
    # view's depth is loose there, and a border measured at a wrong magnification costs the
    # two-view stages extra iterations to undo.
    fine = index > 0 and stage.scale >= 0.5 * finest_scale and set(stage.views) == set(setup.used_views) and index < planned
    if fine and not (problem.partial or setup.tracking or run.partial_checked):
        # The first fine stage: does a live start explain every vessel with part of the model unmatched?
        run.partial_checked = True
        problem.partial = any(looks_partial(problem.match_fractions(pose, stage.views)) for pose in run.poses)
    if options.border_correction and fine:
        problem.update_border_shifts(run.pose_history[-1], stage.views)
    if not stage.all_starts and len(run.poses) > 1:
        run.other = _runner_up(problem, stage, run.poses)
        run.poses, run.starts_agreeing = _keep_best(problem, stage, run.poses)
    dtype = torch.float64 if (stage.optimizer == "lbfgs" if stage.float64 is None else stage.float64) else torch.float32
    increment = PoseIncrement(run.poses, problem.centre, problem.radius_mm)
    # Fine levels with one start (every tracking stage) evaluate the loss in a window.
    windowed = len(run.poses) == 1 and (setup.tracking or stage.scale >= 0.5 * finest_scale)
    if windowed:
        problem.set_windows(stage, run.poses, dtype)
    delta, outcome = _optimize(problem, stage, increment, dtype, reporter, min(index, planned - 1))
    if windowed and not problem.windows_hold(stage, increment.poses(delta.detach()), dtype):
        # The pose left its window (a large step): redo the stage on the whole image.
        problem.windows.clear()
        delta, outcome = _optimize(problem, stage, increment, dtype, reporter, min(index, planned - 1))
    run.poses, run.outcome = increment.poses(delta.detach()), outcome
    if outcome.final_loss is not None and len(run.poses) == 1:
        per_start = torch.tensor([outcome.final_loss])
    else:
        with torch.no_grad():
            per_start = problem.loss(torch.as_tensor(run.poses), stage, dtype)
    best_index = int(torch.argmin(per_start))
    run.final_loss = float(per_start[best_index])
    run.iterations[stage.name] = outcome.iterations
    run.seconds[stage.name] = round(outcome.seconds, 4)
    run.loss_history.append((stage.name, outcome.losses))
    run.pose_history.append(run.poses[best_index])
    run.frames.extend((stage.name, it, snapshot[best_index]) for it, snapshot in reporter.snapshots)
    if reporter.progress is not None:
        reporter.progress({"stage": stage.name, "iteration": outcome.iterations, "loss": run.final_loss,
                           "fraction": reporter.plan.stage_done(min(index, planned - 1))})
    if index >= planned - 1 and len(run.poses) > 1:
        run.poses, run.starts_agreeing = _keep_best(problem, stage, run.poses)
    elif len(run.poses) > 1 and index + 1 < planned and not setup.stages[index + 1].add_initial_starts:
        # Starts that reached the same pose need not all be carried on: keep the best of each group.
        run.poses, agreeing = _distinct(problem, run.poses, per_start.detach().cpu().numpy())
        run.starts_agreeing = agreeing if len(run.poses) == 1 else run.starts_agreeing


def _optimize(problem: _Problem, stage: Stage, increment: PoseIncrement, dtype: torch.dtype, reporter: _Reporter,
              progress_index: int) -> tuple[torch.Tensor, _StageOutcome]:
    """Run the stage's optimizer from a zero increment; returns the final increment ``(B, 6)`` and the outcome."""
    delta = torch.zeros((len(increment.base), 6), dtype=torch.float64, requires_grad=True)
    reporter.begin(progress_index, increment, delta)
    return delta, _RUNNERS[stage.optimizer](problem, stage, increment, delta, dtype, reporter)


def _summary(setup: _Setup, run: _Run, options: RegistrationOptions, total_seconds: float,
             target_points: np.ndarray | None) -> RegistrationResult:
    """The result: the kept pose, per-view overlaps, and metrics (stages, convergence, confidence, ground truth)."""
    problem, used_views, initial = setup.problem, setup.used_views, setup.initial
    mesh, rig = problem.mesh, problem.rig
    estimate = run.poses[0]
    view_results = _view_results(problem, initial, estimate)
    converged, reason = _convergence(run.outcome, view_results)
    metrics = {
        "loss": run.final_loss,
        "iterations": run.iterations,
        "seconds": {**run.seconds, "total": round(total_seconds, 4)},
        "device": str(problem.device),
        "converged": converged,
        "reason": reason,
        "starts": len(setup.starts),
        "starts_agreeing": run.starts_agreeing,
        "initialization": setup.searched.metrics() if setup.searched is not None else GIVEN_INITIALIZATION,
        "configuration": options.configuration,
    }
    points = mesh.vertices if target_points is None else target_points
    if setup.tracking:
        metrics["mode"] = "track"
        metrics["motion"] = motion_between(initial, estimate, points)
    if options.border_correction:
        metrics["border_shift_px"] = {name: round(problem.border_shift_px[name], 4) for name in used_views}
    metrics["confidence"] = _confidence(problem, estimate, view_results, run.other, run.outcome, used_views, setup.searched)
    if len(used_views) == 1:
        metrics["warnings"] = [
            (f"single-view registration ({used_views[0]}): translation along that view's central ray and "
             "out-of-plane rotation are only weakly determined by one silhouette; check the pose with the "
             "other view (its dice is reported when its mask is given) or register with both views")
        ]
    if options.ground_truth_mesh_to_world is not None:
        truth = validate_rigid(options.ground_truth_mesh_to_world, field="options.ground_truth_mesh_to_world", allow_mirror=False)
        metrics["ground_truth"] = ground_truth_errors(estimate, truth, rig.views, mesh.vertices, target_points)
        metrics["ground_truth"]["initial_mtre_mm"] = mean_distance_mm(initial, truth, points)
    return RegistrationResult(estimate, initial, view_results, metrics, run.loss_history, run.pose_history, run.frames)


def _border_moved(problem: _Problem, options: RegistrationOptions, stage: Stage, used_views, pose: np.ndarray) -> bool:
    """Re-measure the border shifts at the final pose of a refinement; True when one moved by more
    than BORDER_RECHECK_PX (the stage is then run once more with them). The first measurement is
    taken at the last Adam level's pose: on small images (the phantom at 256 px) that pose can be
    far enough off to measure a border 0.3–0.6 px wrong, which the final fit then keeps."""
    if not (options.border_correction and stage.optimizer == "lbfgs" and set(stage.views) == set(used_views)):
        return False
    before = dict(problem.border_shift_px)
    problem.update_border_shifts(pose, stage.views)
    if max(abs(problem.border_shift_px[name] - before[name]) for name in stage.views) > BORDER_RECHECK_PX:
        return True
    problem.border_shift_px = before  # the fit used these: keep them (and report them)
    return False


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


def _initialize(mesh: TriangleMesh, masks: dict[str, np.ndarray], rig: Rig, options: RegistrationOptions):
    """The searched starts (:class:`~.initialization.Initialization`), or None to use the given pose."""
    pose_given = rig.initial_pose_given or options.initial_mesh_to_world is not None
    if resolve_initialization(options.initialization, pose_given) != "search":
        return None
    visible = {name: mask for name, mask in masks.items()
               if name in rig.views and mask.shape == rig.views[name].image_size[::-1] and mask.any()}
    found = search_initial_poses(mesh, visible, rig, max(options.starts, SEARCH_MIN_STARTS))
    if not found.partial_search_needed:
        return found
    return with_branch_starts(found, mesh, visible, rig)


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


def _keep_best(problem: _Problem, stage: Stage, poses: np.ndarray) -> tuple[np.ndarray, int]:
    """Keep the start with the lowest loss at ``stage``; count the starts that agree with it."""
    with torch.no_grad():
        losses = problem.loss(torch.as_tensor(poses), stage, torch.float32)
    best = poses[int(torch.argmin(losses))]
    return best[None], _agreeing(problem, poses, best)


def _distinct(problem: _Problem, poses: np.ndarray, losses: np.ndarray) -> tuple[np.ndarray, int]:
    """The poses, best first, less those within AGREEMENT_ADD_MM of a better one; and how many agree with the best."""
    kept: list[np.ndarray] = []
    for index in np.argsort(losses, kind="stable"):
        if all(mean_distance_mm(poses[index], other, problem.mesh.vertices) >= AGREEMENT_ADD_MM for other in kept):
            kept.append(poses[index])
    return np.stack(kept), _agreeing(problem, poses, kept[0])


def _agreeing(problem: _Problem, poses: np.ndarray, best: np.ndarray) -> int:
    """How many of ``poses`` lie within AGREEMENT_ADD_MM (ADD) of ``best``."""
    return int(sum(mean_distance_mm(pose, best, problem.mesh.vertices) < AGREEMENT_ADD_MM for pose in poses))


def _runner_up(problem: _Problem, stage: Stage, poses: np.ndarray) -> dict | None:
    """The best start that ended elsewhere and how well it and the best fit, see :mod:`.confidence`."""
    with torch.no_grad():
        losses = problem.loss(torch.as_tensor(poses), stage, torch.float32).numpy()
    found = runner_up(poses, losses, problem.mesh.vertices, max(AGREEMENT_ADD_MM, DISTINCT_RADIUS_FRACTION * problem.radius_mm))
    if found is None:
        return None
    index, distance = found
    vertices, faces = problem.mesh_tensors(torch.float64)
    fits = []
    for pose in (poses[int(np.argmin(losses))], poses[index]):
        per_view = []
        for name in stage.views:
            view = problem.rig.views[name]
            mesh_to_view = torch.as_tensor(view.world_to_view @ pose, device=problem.device)[None]
            silhouette = render_hard_silhouette(vertices, faces, mesh_to_view, Camera.from_view(view))[0].cpu().numpy()
            per_view.append(tolerant_f_score(silhouette, problem.masks[name], ConfidenceThresholds().fit_tolerance_px))
        fits.append(float(np.mean(per_view)))
    return {"distance_mm": round(distance, 2), "best_fit": round(fits[0], 4), "fit": round(fits[1], 4)}


def _confidence(problem, estimate, views, other, outcome, used_views, searched: Initialization | None) -> dict:
    world = problem.mesh.vertices @ estimate[:3, :3].T + estimate[:3, 3]
    fitted = {  # Dice against the target actually fitted: the mask with its border moved by the correction
        name: dice(views[name].silhouette, shifted_mask(problem.targets[name], problem.border_shift_px[name],
                                                        problem.signed_distance(name)) >= 0.5)
        for name in used_views
    }
    return assess({
        "dice": {name: round(fitted[name], 4) for name in used_views},
        "runner_up": other,
        "border_shift_px": {name: round(problem.border_shift_px[name], 3) for name in used_views},
        "outside_fraction": {name: round(outside_fraction(problem.rig.views[name], world), 4) for name in used_views},
        "stopped_on_tolerance": outcome is not None and outcome.stopped_by == "tolerance",
        **_match_signals({name: match_fractions(views[name].silhouette, problem.masks[name]) for name in used_views}),
        "partial_loss": problem.partial,
        "part_runner_up": (searched.branch or {}).get("runner_up") if searched is not None else None,
    })


def _match_signals(fractions: dict[str, dict]) -> dict:
    """``unmatched_fraction`` / ``uncovered_fraction`` per view, rounded (see :mod:`.partial`)."""
    return {f"{key}_fraction": {name: round(value[key], 4) for name, value in fractions.items()}
            for key in ("unmatched", "uncovered")}


def _view_results(problem: _Problem, initial: np.ndarray, estimate: np.ndarray) -> dict[str, ViewResult]:
    vertices, faces = problem.mesh_tensors(torch.float64)
    results = {}
    for name, view in problem.rig.views.items():
        if name not in problem.masks:
            continue
        camera = Camera.from_view(view)
        poses = torch.as_tensor(np.stack([view.world_to_view @ initial, view.world_to_view @ estimate]), device=problem.device)
        silhouettes = render_hard_silhouette(vertices, faces, poses, camera).cpu().numpy()
        mesh_to_view = view.world_to_view @ estimate
        mask = problem.masks[name]
        results[name] = ViewResult(
            world_to_view=view.world_to_view,
            mesh_to_view=mesh_to_view,
            projection_matrix=view.intrinsic_matrix @ mesh_to_view[:3],
            dice=dice(silhouettes[1], mask),
            iou=iou(silhouettes[1], mask),
            silhouette=silhouettes[1],
            initial_silhouette=silhouettes[0],
        )
    return results


def _convergence(outcome: _StageOutcome | None, views: dict[str, ViewResult]) -> tuple[bool, str]:
    low = ", ".join(f"{name} {result.dice:.3f}" for name, result in views.items() if result.dice < MIN_CONVERGED_DICE)
    if low:
        return False, f"silhouettes overlap poorly after optimization (dice {low}); the pose is likely wrong"
    if outcome is None or outcome.stopped_by != "tolerance":
        return False, "iteration limit reached before the pose stopped changing"
    return True, "pose change below tolerance in the final stage"
