"""Imaging geometry of one X-ray view and of a biplane rig.

The convention (written once, here; the README repeats it):

* **World frame**: millimetres. The vessel mesh is placed in it by a rigid
  ``mesh_to_world`` 4x4 — the unknown that registration estimates.
* **View frame** of one X-ray view: origin at the X-ray source; +z along the central
  ray from the source toward the detector; +x along increasing image columns ``u``;
  +y along increasing image rows ``v``. Because +x/+y follow the *stored* image axes,
  a real detector can make this frame left-handed, so the 3x3 part of
  ``world_to_view`` is orthonormal with determinant +1 **or -1**.
* **Projection** of a view-frame point ``(x, y, z)``, ``z > 0``::

      u = u0 + (sid_mm / du) * x / z
      v = v0 + (sid_mm / dv) * y / z

  with ``(du, dv) = pixel_spacing_mm`` (column, row spacing at the detector) and
  ``(u0, v0) = principal_point_px``.
* **Pixel centres**: pixel (column ``i``, row ``j``) has its centre at ``(u, v) = (i, j)``;
  the image covers ``u ∈ [-0.5, W-0.5]``, ``v ∈ [-0.5, H-0.5]``. Arrays are indexed
  ``image[j, i]`` (row first), shape ``(H, W)``.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from ..errors import DsaregInputError
from .pose import invert_rigid, make_transform, rotation_about_axis, validate_rigid

VIEW_NAMES = ("ap", "lat")
"""The two planes of a biplane C-arm, in the order dsareg reports them."""


@dataclass(frozen=True)
class ViewGeometry:
    """Intrinsics and extrinsics of one X-ray view (see the module docstring for frames).

    Attributes:
        image_size: ``(W, H)`` in pixels.
        pixel_spacing_mm: ``(du, dv)``: column and row spacing at the detector, mm.
        sid_mm: Source-to-detector distance along the central ray, mm.
        principal_point_px: ``(u0, v0)``: where the central ray meets the image, px.
        world_to_view: 4x4 float64, orthonormal 3x3 part (det ±1).
    """

    image_size: tuple[int, int]
    pixel_spacing_mm: tuple[float, float]
    sid_mm: float
    principal_point_px: tuple[float, float]
    world_to_view: np.ndarray = field(repr=False)

    def __post_init__(self) -> None:
        width, height = (int(x) for x in self.image_size)
        if width < 1 or height < 1:
            raise DsaregInputError(f"image_size {list(self.image_size)} is empty", field="image_size")
        du, dv = (float(x) for x in self.pixel_spacing_mm)
        if not (du > 0 and dv > 0 and np.isfinite(du) and np.isfinite(dv)):
            raise DsaregInputError("pixel spacing must be positive", field="pixel_spacing_mm")
        if not (self.sid_mm > 0 and np.isfinite(self.sid_mm)):
            raise DsaregInputError("must be a positive distance in mm", field="sid_mm")
        if not np.all(np.isfinite(self.principal_point_px)):
            raise DsaregInputError("must be finite", field="principal_point_px")
        object.__setattr__(self, "image_size", (width, height))
        object.__setattr__(self, "pixel_spacing_mm", (du, dv))
        object.__setattr__(self, "sid_mm", float(self.sid_mm))
        object.__setattr__(self, "principal_point_px", tuple(float(x) for x in self.principal_point_px))
        object.__setattr__(
            self, "world_to_view", validate_rigid(self.world_to_view, field="world_to_view", allow_mirror=True)
        )

    # ---- derived quantities -------------------------------------------------------
    @property
    def width(self) -> int:
        return self.image_size[0]

    @property
    def height(self) -> int:
        return self.image_size[1]

    @property
    def focal_px(self) -> tuple[float, float]:
        """``(fx, fy) = (sid/du, sid/dv)`` in pixels."""
        return (self.sid_mm / self.pixel_spacing_mm[0], self.sid_mm / self.pixel_spacing_mm[1])

    @property
    def intrinsic_matrix(self) -> np.ndarray:
        """3x3 ``K`` mapping view-frame rays to homogeneous pixels."""
        fx, fy = self.focal_px
        u0, v0 = self.principal_point_px
        return np.array([[fx, 0.0, u0], [0.0, fy, v0], [0.0, 0.0, 1.0]])

    @property
    def projection_matrix(self) -> np.ndarray:
        """3x4 ``P = K [R | t]`` mapping homogeneous world mm to homogeneous pixels."""
        return self.intrinsic_matrix @ self.world_to_view[:3]

    @property
    def is_mirrored(self) -> bool:
        """True when the view frame is left-handed relative to the world (det −1)."""
        return bool(np.linalg.det(self.world_to_view[:3, :3]) < 0)

    @property
    def source_position_world(self) -> np.ndarray:
        """X-ray source position in world mm, shape ``(3,)``."""
        return invert_rigid(self.world_to_view)[:3, 3]

    # ---- operations -----------------------------------------------------------------
    def project(self, points_world: np.ndarray) -> np.ndarray:
        """Project world points ``(N, 3)`` mm to pixel coordinates ``(N, 2)`` as ``(u, v)``."""
        points = np.asarray(points_world, dtype=np.float64)
        view = points @ self.world_to_view[:3, :3].T + self.world_to_view[:3, 3]
        fx, fy = self.focal_px
        u0, v0 = self.principal_point_px
        return np.stack([u0 + fx * view[:, 0] / view[:, 2], v0 + fy * view[:, 1] / view[:, 2]], axis=1)

    def resized(self, width: int, height: int) -> "ViewGeometry":
        """The same view sampled on a ``width × height`` pixel grid covering the same detector.

        Pixel centres keep their convention: new ``u' = s (u + 0.5) − 0.5`` with
        ``s = width / W``; the pixel spacing grows by ``1/s`` so the focal length in
        pixels scales by ``s`` and the source-to-detector distance is unchanged.
        """
        scale_u, scale_v = width / self.width, height / self.height
        u0, v0 = self.principal_point_px
        return replace(
            self,
            image_size=(int(width), int(height)),
            pixel_spacing_mm=(self.pixel_spacing_mm[0] / scale_u, self.pixel_spacing_mm[1] / scale_v),
            principal_point_px=(scale_u * (u0 + 0.5) - 0.5, scale_v * (v0 + 0.5) - 0.5),
        )

    def scaled(self, factor: float) -> "ViewGeometry":
        """``resized`` by a common factor, rounding the image size to whole pixels."""
        return self.resized(max(1, round(self.width * factor)), max(1, round(self.height * factor)))

    def with_world_to_view(self, world_to_view: np.ndarray) -> "ViewGeometry":
        return replace(self, world_to_view=world_to_view)

    def to_dict(self) -> dict:
        """JSON-ready dictionary in the geometry-file layout."""
        return {
            "image_size": list(self.image_size),
            "pixel_spacing_mm": list(self.pixel_spacing_mm),
            "sid_mm": self.sid_mm,
            "principal_point_px": list(self.principal_point_px),
            "world_to_view": self.world_to_view.tolist(),
        }


def default_principal_point(image_size: tuple[int, int]) -> tuple[float, float]:
    """The image centre under the pixel-centre convention: ``((W−1)/2, (H−1)/2)``."""
    return ((image_size[0] - 1) / 2.0, (image_size[1] - 1) / 2.0)


@dataclass(frozen=True)
class Rig:
    """A biplane rig: named views sharing one world frame, plus a starting pose.

    Attributes:
        views: ``{"ap": ViewGeometry, "lat": ViewGeometry}`` (one of them may be absent
            for single-view work).
        initial_mesh_to_world: 4x4 starting estimate of the mesh pose (identity when not given).
        initial_pose_given: whether a pose was given (``None`` above means "unknown": the
            registration then searches for one, see ``options.initialization``).
    """

    views: dict[str, ViewGeometry]
    initial_mesh_to_world: np.ndarray | None = field(default=None, repr=False)
    initial_pose_given: bool = field(init=False, default=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "initial_pose_given", self.initial_mesh_to_world is not None)
        if self.initial_mesh_to_world is None:
            object.__setattr__(self, "initial_mesh_to_world", np.eye(4))
        if not self.views:
            raise DsaregInputError("at least one view is required", field="views", accepted="'ap' and/or 'lat'")
        unknown = set(self.views) - set(VIEW_NAMES)
        if unknown:
            raise DsaregInputError(
                f"unknown view name(s) {sorted(unknown)}", field="views", accepted=f"{list(VIEW_NAMES)}"
            )
        object.__setattr__(
            self,
            "initial_mesh_to_world",
            validate_rigid(self.initial_mesh_to_world, field="initial_mesh_to_world", allow_mirror=False),
        )

    def angle_between_views_deg(self) -> float:
        """Angle between the two central rays (degrees); requires both views."""
        rays = [invert_rigid(self.views[name].world_to_view)[:3, 2] for name in VIEW_NAMES]
        return float(np.degrees(np.arccos(np.clip(np.dot(rays[0], rays[1]), -1.0, 1.0))))

    def to_dict(self) -> dict:
        data: dict = {"views": {name: view.to_dict() for name, view in self.views.items()}}
        if self.initial_pose_given:
            data["initial_mesh_to_world"] = self.initial_mesh_to_world.tolist()
        return data


# ---- constructors from other descriptions -------------------------------------------


def view_from_projection_matrix(
    projection_matrix: np.ndarray,
    image_size: tuple[int, int],
    pixel_spacing_mm: tuple[float, float],
    *,
    front_point_world: np.ndarray | None = None,
    tolerance: float = 1e-3,
) -> ViewGeometry:
    """Recover a view from a 3x4 projection matrix ``P`` (pixels, any scale and sign).

    ``P[:, :3] = λ K R`` is split by RQ decomposition into an upper-triangular ``K``
    with positive diagonal and an orthonormal ``R``; a detector frame that is mirrored
    shows up as ``det R = −1``. The overall sign of ``P`` is fixed by requiring
    ``front_point_world`` (default: the world origin, usually the isocentre) to lie in
    front of the source (view ``z > 0``).

    Raises:
        DsaregInputError: singular ``P``, skew, or focal lengths inconsistent with the
            pixel spacing (``fx·du ≠ fy·dv``).
    """
    field_name = "projection_matrix"
    try:
        p = np.asarray(projection_matrix, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise DsaregInputError("is not numeric", field=field_name, accepted="a 3x4 matrix") from exc
    if p.shape != (3, 4) or not np.all(np.isfinite(p)):
        raise DsaregInputError(f"must be a finite 3x4 matrix, got shape {list(p.shape)}", field=field_name)
    m = p[:, :3]
    if abs(np.linalg.det(m)) < 1e-12 * max(1.0, np.abs(m).max() ** 3):
        raise DsaregInputError("left 3x3 block is singular", field=field_name)
    k, r = _rq(m)
    signs = np.diag(np.sign(np.diag(k)))
    k, r = k @ signs, signs @ r  # K with positive diagonal; R absorbs the signs
    scale = k[2, 2]
    k = k / scale
    t = np.linalg.solve(k, p[:, 3] / scale)
    front = np.zeros(3) if front_point_world is None else np.asarray(front_point_world, dtype=np.float64)
    if r[2] @ front + t[2] < 0:  # P had a negative overall scale: flip the whole frame
        r, t = -r, -t
    if abs(k[0, 1]) > tolerance * k[0, 0]:
        raise DsaregInputError(f"has skew {k[0, 1]:.4g} px; detectors have none", field=field_name)
    du, dv = (float(x) for x in pixel_spacing_mm)
    sid_u, sid_v = k[0, 0] * du, k[1, 1] * dv
    if abs(sid_u - sid_v) > tolerance * max(sid_u, sid_v):
        raise DsaregInputError(
            f"focal lengths give different source-detector distances ({sid_u:.2f} vs {sid_v:.2f} mm) "
            f"for pixel spacing {[du, dv]}",
            field="pixel_spacing_mm",
            accepted="a spacing whose column/row ratio matches fy/fx of P",
        )
    return ViewGeometry(
        image_size=image_size,
        pixel_spacing_mm=(du, dv),
        sid_mm=0.5 * (sid_u + sid_v),
        principal_point_px=(k[0, 2], k[1, 2]),
        world_to_view=make_transform(r, t),
    )


def _rq(matrix: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """RQ decomposition ``M = R_upper @ Q`` of a 3x3 matrix via numpy's QR."""
    flip = np.flipud(np.eye(3))
    q, r = np.linalg.qr((flip @ matrix).T)
    upper = flip @ r.T @ flip
    orthonormal = flip @ q.T
    return upper, orthonormal


def view_from_detector_pose(
    image_size: tuple[int, int],
    pixel_spacing_mm: tuple[float, float],
    detector_to_world: np.ndarray,
    source_position_world: np.ndarray,
) -> ViewGeometry:
    """Build a view from a detector placement (the ``.rad`` header description).

    The detector frame has pixel (column ``i``, row ``j``) centred at
    ``(i·du, j·dv, 0)`` mm and its +z axis pointing toward the source;
    ``detector_to_world`` (``TPosition``) maps it to world mm. With the source at
    ``s = T⁻¹ S`` in detector mm: ``sid = s_z``, ``(u0, v0) = (s_x/du, s_y/dv)``, and the
    view frame is the detector frame shifted to the source with z reversed — a mirror
    (det −1) of a right-handed detector frame.
    """
    detector_to_world = validate_rigid(detector_to_world, field="TPosition", allow_mirror=True)
    source = np.asarray(source_position_world, dtype=np.float64).reshape(3)
    s = invert_rigid(detector_to_world) @ np.append(source, 1.0)
    if s[2] <= 0:
        raise DsaregInputError(
            f"source lies {s[2]:.1f} mm from the detector plane on the wrong side",
            field="SourcePosition",
            accepted="a source on the +z side of the detector (TPosition z points to the source)",
        )
    du, dv = (float(x) for x in pixel_spacing_mm)
    detector_to_view = np.array(
        [[1.0, 0.0, 0.0, -s[0]], [0.0, 1.0, 0.0, -s[1]], [0.0, 0.0, -1.0, s[2]], [0.0, 0.0, 0.0, 1.0]]
    )
    return ViewGeometry(
        image_size=image_size,
        pixel_spacing_mm=(du, dv),
        sid_mm=float(s[2]),
        principal_point_px=(s[0] / du, s[1] / dv),
        world_to_view=detector_to_view @ invert_rigid(detector_to_world),
    )


def rotated_view(
    view: ViewGeometry, angle_deg: float, axis_world: np.ndarray, isocentre_world: np.ndarray | None = None
) -> ViewGeometry:
    """The same imaging chain turned by ``angle_deg`` about an axis through the isocentre.

    The source and detector move together (a C-arm rotation): ``view_to_world`` is
    pre-multiplied by the rotation, so ``world_to_view' = world_to_view · G⁻¹`` with
    ``G`` the rotation about ``axis_world`` (right-hand rule) through
    ``isocentre_world`` (default: world origin).
    """
    centre = np.zeros(3) if isocentre_world is None else np.asarray(isocentre_world, dtype=np.float64)
    rotation = rotation_about_axis(axis_world, np.radians(angle_deg))
    turn = make_transform(rotation, centre - rotation @ centre)
    return view.with_world_to_view(view.world_to_view @ invert_rigid(turn))


def biplane_rig(
    ap_view: ViewGeometry,
    angle_deg: float = 90.0,
    axis_world: np.ndarray = (0.0, 1.0, 0.0),
    isocentre_world: np.ndarray | None = None,
    initial_mesh_to_world: np.ndarray | None = None,
) -> Rig:
    """A rig whose lateral plane is the AP plane turned by ``angle_deg`` (90° = the paper's W)."""
    lat_view = rotated_view(ap_view, angle_deg, np.asarray(axis_world, dtype=np.float64), isocentre_world)
    return Rig(
        views={"ap": ap_view, "lat": lat_view},
        initial_mesh_to_world=initial_mesh_to_world,
    )
