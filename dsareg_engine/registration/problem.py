"""The registration problem shared by all stages: the mesh (or the part of it fitted), the rig, the per-level
targets (border shift, partial-visibility weights) and the loss of a batch of poses, evaluated in a window
around the target and the mesh where a stage allows it."""

from __future__ import annotations

import numpy as np
import torch

from ..geometry.rig import Rig
from ..geometry.vessel_tree import compact
from ..mesh import TriangleMesh
from ..render import Camera, SilhouetteSettings, render_hard_silhouette, render_soft_silhouette
from ..vision.vessel_target import binary_mask
from .border import update_border_shift
from .level_of_detail import _decimated, level_of_detail_faces, mean_projected_face_area_px
from .options import RegistrationOptions
from .parameterization import mesh_radius_mm
from .partial import MATCH_TOLERANCE_PX, _near, match_fractions, trimmed_weight, view_looks_partial
from .schedule import Stage
from .targets import ViewTarget, gaussian_blur, level_target, signed_border_distance

WINDOW_MARGIN_PX = 12.0
"""Room (px of the stage's image) left around the mesh's footprint when a stage's loss is windowed."""


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
        self._mask_near: dict[str, np.ndarray] = {}
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
        return {name: match_fractions(self._hard_silhouette(name, mesh_to_world), self.masks[name],
                                      mask_near=self.mask_near(name)) for name in views}

    def looks_partial(self, mesh_to_world: np.ndarray, views: tuple[str, ...]) -> bool:
        """:func:`.partial.looks_partial` of :meth:`match_fractions`, view by view (:func:`.partial.view_looks_partial`):
        the first view that rules partial visibility out ends it; the usual answer, no, then costs one hard render
        and no distance transform (the mask's is kept, :meth:`mask_near`)."""
        return all(view_looks_partial(self._hard_silhouette(name, mesh_to_world), self.masks[name], self.mask_near(name))
                   for name in views)

    def mask_near(self, view_name: str) -> np.ndarray:
        """``(H, W)`` bool: within :data:`.partial.MATCH_TOLERANCE_PX` of the view's vessels, computed once."""
        if view_name not in self._mask_near:
            self._mask_near[view_name] = _near(self.masks[view_name], MATCH_TOLERANCE_PX)
        return self._mask_near[view_name]

    def _hard_silhouette(self, view_name: str, mesh_to_world: np.ndarray) -> np.ndarray:
        """``(H, W)`` bool: the whole mesh's hard silhouette in the view at ``mesh_to_world``, full resolution."""
        vertices, faces = self.mesh_tensors(torch.float64)
        view = self.rig.views[view_name]
        pose = torch.as_tensor(view.world_to_view @ mesh_to_world, device=self.device)[None]
        return render_hard_silhouette(vertices, faces, pose, Camera.from_view(view))[0].cpu().numpy()

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
