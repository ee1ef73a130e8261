"""Biplane rigs shaped like real C-arms, for tests and benchmarks (no patient data needed).

A clinical biplane differs from the paper's synthetic set-up in ways that catch geometry
bugs: planes not at 90° (e.g. 107°), a detector read out mirrored (the view frame is
left-handed, det −1), a different source–detector distance per plane, the isocentre off
the image centre. Each view here is built as: an AP chain (source at world
``(0, 0, −sod)``, central ray along world +z, image columns along world +x, rows along
+y), turned by its angle about world +y through the isocentre (the world origin) with
:func:`~dsareg_engine.geometry.rig.rotated_view`, then optionally mirrored in ``u``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..geometry.rig import Rig, ViewGeometry, rotated_view
from ..mesh import TriangleMesh


@dataclass(frozen=True)
class CArmPlane:
    """One imaging plane.

    Attributes:
        angle_deg: turn about world +y from the AP position (right-hand rule).
        sod_mm: source to isocentre; sid_mm: source to detector.
        detector_mm: width of the detector; size_px: image width in pixels (square pixels).
        rows_px: image height in pixels (None: square, ``size_px``), e.g. 774 for a 1000-px-wide detector.
        mirrored: image columns run against the view frame's right-handed x (det −1).
        principal_offset_px: where the central ray meets the image, relative to the centre.
    """

    angle_deg: float
    sod_mm: float = 750.0
    sid_mm: float = 1100.0
    detector_mm: float = 300.0
    size_px: int = 256
    mirrored: bool = False
    principal_offset_px: tuple[float, float] = (0.0, 0.0)
    rows_px: int | None = None

    def view(self) -> ViewGeometry:
        world_to_view = np.eye(4)
        world_to_view[2, 3] = self.sod_mm  # the isocentre lies sod_mm in front of the source
        if self.mirrored:
            world_to_view = np.diag([-1.0, 1.0, 1.0, 1.0]) @ world_to_view
        spacing = self.detector_mm / self.size_px
        rows = self.rows_px or self.size_px
        ap = ViewGeometry(
            image_size=(self.size_px, rows),
            pixel_spacing_mm=(spacing, spacing),
            sid_mm=self.sid_mm,
            principal_point_px=((self.size_px - 1) / 2.0 + self.principal_offset_px[0],
                                (rows - 1) / 2.0 + self.principal_offset_px[1]),
            world_to_view=world_to_view,
        )
        return rotated_view(ap, self.angle_deg, np.array([0.0, 1.0, 0.0]))


def clinical_biplane_rig(size_px: int = 256, angle_between_deg: float = 107.0, detector_mm: float = 400.0,
                         rows_px: int | None = None) -> Rig:
    """AP at −10°, LAT ``angle_between_deg`` further, LAT mirrored, SIDs 1100 / 1200 mm, SODs 750 / 800 mm;
    images ``size_px`` wide and ``rows_px`` high (None: square), ``detector_mm`` wide (square pixels).

    No initial pose (``rig.initial_pose_given`` is False), like a geometry read from DICOM headers.
    """
    offset = size_px / 100.0
    ap = CArmPlane(-10.0, 750.0, 1100.0, detector_mm, size_px, False, (3.0 * offset, -2.0 * offset), rows_px)
    lat = CArmPlane(-10.0 + angle_between_deg, 800.0, 1200.0, detector_mm, size_px, True, (-4.0 * offset, 5.0 * offset),
                    rows_px)
    return Rig(views={"ap": ap.view(), "lat": lat.view()})


def uniform_rotation(rng: np.random.Generator) -> np.ndarray:
    """A rotation ``(3, 3)`` drawn uniformly over SO(3) (normalized Gaussian quaternion)."""
    from ..registration.search.rotation_grid import quaternions_to_matrices

    quaternion = rng.normal(size=4)
    return quaternions_to_matrices((quaternion / np.linalg.norm(quaternion))[None])[0]


def random_visible_pose(mesh: TriangleMesh, rig: Rig, rng: np.random.Generator, radius_mm: float = 60.0,
                        tries: int = 200) -> np.ndarray:
    """``mesh_to_world`` with a uniform random rotation and the mesh centre uniform in a ball of
    ``radius_mm`` about the isocentre, redrawn until every vertex projects inside every view
    (the last draw is returned after ``tries``)."""
    pose = np.eye(4)
    for _ in range(tries):
        pose[:3, :3] = uniform_rotation(rng)
        direction = rng.normal(size=3)
        centre = radius_mm * rng.random() ** (1.0 / 3.0) * direction / np.linalg.norm(direction)
        pose[:3, 3] = centre - pose[:3, :3] @ mesh.centroid
        if all(_inside(view, mesh.transformed(pose).vertices) for view in rig.views.values()):
            break
    return pose


def _inside(view: ViewGeometry, points_world: np.ndarray) -> bool:
    pixels = view.project(points_world)
    return bool(np.all((pixels >= -0.5) & (pixels <= np.array(view.image_size) - 0.5)))


def render_masks(mesh: TriangleMesh, rig: Rig, mesh_to_world: np.ndarray) -> dict[str, np.ndarray]:
    """Hard silhouettes ``{view: (H, W) bool}`` of the mesh at ``mesh_to_world``."""
    import torch

    from ..render import Camera, render_hard_silhouette

    vertices, faces = mesh.torch(torch.float64)
    return {
        name: render_hard_silhouette(vertices, faces, torch.as_tensor(view.world_to_view @ mesh_to_world)[None],
                                     Camera.from_view(view))[0].numpy()
        for name, view in rig.views.items()
    }
