"""Geometry files (JSON) and named presets.

A geometry file describes a rig in world millimetres::

    {"views": {
       "ap":  {"image_size": [1000, 774], "pixel_spacing_mm": [0.382, 0.382], "sid_mm": 1196.4,
               "principal_point_px": [434.6, 384.5], "world_to_view": [[...4x4...]]},
       "lat": {"image_size": ..., "pixel_spacing_mm": ..., "projection_matrix": [[...3x4...]]}},
     "initial_mesh_to_world": [[...4x4...]]}

Each view gives either ``sid_mm`` + ``world_to_view`` (``principal_point_px`` defaults
to the image centre) or a 3x4 ``projection_matrix`` in pixels. Instead of a second
view, ``"lat_from_ap": {"angle_deg": 90, "axis_world": [0, 1, 0], "isocentre_world": [0, 0, 0]}``
turns the AP chain about an axis through the isocentre. Validation errors name the
field at fault. What a geometry *argument* is (preset, JSON, file) is decided in one place,
:func:`dsareg_engine.geometry.spec.parse_geometry`, which also writes the canonical stored form.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, PositiveFloat, PositiveInt, ValidationError, model_validator

from ..errors import DsaregInputError
from .rig import (
    Rig,
    ViewGeometry,
    default_principal_point,
    rotated_view,
    view_from_projection_matrix,
)
from .pose import invert_rigid, look_at_world_to_view

Matrix = list[list[float]]


class ViewSpec(BaseModel):
    """One X-ray view. Either `sid_mm` + `world_to_view` (+ optional `principal_point_px`) or a
    `projection_matrix`."""

    model_config = ConfigDict(extra="forbid", json_schema_extra={"examples": [{
        "image_size": [800, 800], "pixel_spacing_mm": [0.3, 0.3], "sid_mm": 1200.0,
        "principal_point_px": [399.5, 399.5],
        "world_to_view": [[0, 0, -1, 0], [0, 1, 0, 0], [1, 0, 0, 750], [0, 0, 0, 1]]}]})

    image_size: tuple[PositiveInt, PositiveInt] = Field(
        description="[width, height] of the image in pixels.", examples=[[800, 800]])
    pixel_spacing_mm: tuple[PositiveFloat, PositiveFloat] = Field(
        description="[column, row] pixel spacing at the detector, mm (DICOM Imager Pixel Spacing).",
        examples=[[0.3, 0.3]])
    sid_mm: PositiveFloat | None = Field(None, description="Source-to-detector distance, mm.", examples=[1200.0])
    principal_point_px: tuple[float, float] | None = Field(
        None, description="[u0, v0] foot of the central ray on the image, pixels; default the image centre "
                          "((W-1)/2, (H-1)/2).")
    world_to_view: Matrix | None = Field(
        None, description="4x4 rigid transform world mm → view frame (origin at the source, +z along the central "
                          "ray toward the detector, +x along columns, +y along rows); det may be -1 (mirror).")
    projection_matrix: Matrix | None = Field(
        None, description="3x4 world mm → homogeneous pixels, instead of sid_mm + world_to_view.")

    @model_validator(mode="after")
    def _one_description(self) -> ViewSpec:
        explicit = self.sid_mm is not None or self.world_to_view is not None
        if self.projection_matrix is not None and explicit:
            raise ValueError("give either projection_matrix or sid_mm + world_to_view, not both")
        if self.projection_matrix is None and (self.sid_mm is None or self.world_to_view is None):
            raise ValueError("needs sid_mm and world_to_view (or a projection_matrix)")
        return self

    def build(self) -> ViewGeometry:
        if self.projection_matrix is not None:
            return view_from_projection_matrix(self.projection_matrix, self.image_size, self.pixel_spacing_mm)
        return ViewGeometry(
            image_size=self.image_size,
            pixel_spacing_mm=self.pixel_spacing_mm,
            sid_mm=self.sid_mm,
            principal_point_px=self.principal_point_px or default_principal_point(self.image_size),
            world_to_view=np.asarray(self.world_to_view, dtype=np.float64),
        )


class LatFromAp(BaseModel):
    """The lateral view as the AP imaging chain turned about an axis through the isocentre."""

    model_config = ConfigDict(extra="forbid")

    angle_deg: float = Field(description="Rotation angle, degrees (90 for an orthogonal biplane).", examples=[90.0])
    axis_world: tuple[float, float, float] = Field((0.0, 1.0, 0.0), description="Rotation axis, world frame.")
    isocentre_world: tuple[float, float, float] = Field((0.0, 0.0, 0.0), description="Isocentre, world mm.")


class RigSpec(BaseModel):
    """A whole geometry file."""

    model_config = ConfigDict(extra="forbid")

    views: dict[str, ViewSpec] = Field(description="The views by name: `ap` and `lat`.")
    lat_from_ap: LatFromAp | None = Field(None, description="Derive `lat` from `ap` (then give only `ap`).")
    initial_mesh_to_world: Matrix | None = Field(
        None, description="4x4 rigid initial pose mesh mm → world mm where the optimization starts (default identity).")


def rig_from_dict(data: Any) -> Rig:
    """Validate a parsed geometry file and build the :class:`Rig`.

    Raises:
        DsaregInputError: the message names the field at fault (``views.ap.sid_mm``...).
    """
    try:
        spec = RigSpec.model_validate(data)
    except ValidationError as exc:
        first = exc.errors()[0]
        location = ".".join(str(part) for part in first["loc"])
        raise DsaregInputError(
            first["msg"], field=f"geometry.{location}" if location else "geometry", accepted=_ACCEPTED
        ) from None
    views: dict[str, ViewGeometry] = {}
    for name, view_spec in spec.views.items():
        try:
            views[name] = view_spec.build()
        except DsaregInputError as exc:
            raise exc.with_field_prefix(f"geometry.views.{name}") from None
    if spec.lat_from_ap is not None:
        if "ap" not in views or "lat" in views:
            raise DsaregInputError("needs an 'ap' view and no 'lat' view", field="geometry.lat_from_ap")
        turn = spec.lat_from_ap
        views["lat"] = rotated_view(views["ap"], turn.angle_deg, np.array(turn.axis_world), np.array(turn.isocentre_world))
    try:
        return Rig(views=views, initial_mesh_to_world=spec.initial_mesh_to_world)
    except DsaregInputError as exc:
        raise exc.with_field_prefix("geometry") from None


_ACCEPTED = "a JSON object {'views': {'ap': {...}, 'lat': {...}}, 'initial_mesh_to_world': 4x4} or a preset name"


def save_rig(rig: Rig, path: str | Path) -> None:
    """Write ``rig`` as an explicit geometry file (``load_rig`` in :mod:`dsareg_engine.geometry.spec` reads it)."""
    Path(path).write_text(json.dumps(rig.to_dict(), indent=2))


# ---- presets --------------------------------------------------------------------------

PAPER_IMAGE_SIZE = 800
PAPER_FOV_DEG = 60.0
PAPER_CAMERA_DISTANCE_MM = 150.0
PAPER_PIXEL_SPACING_MM = 1.0
"""Nominal; only ``sid/spacing`` (the focal length in px) matters to the projection."""


def paper_focal_px(image_size: int = PAPER_IMAGE_SIZE, fov_deg: float = PAPER_FOV_DEG) -> float:
    """Focal length of PyTorch3D's FoVPerspectiveCameras: ``(S/2) / tan(fov/2)`` (692.82 px at 800, 60°)."""
    return (image_size / 2.0) / np.tan(np.radians(fov_deg) / 2.0)


def pytorch3d_camera_position(distance: float, elevation_deg: float, azimuth_deg: float) -> np.ndarray:
    """Camera centre used by PyTorch3D's ``look_at_view_transform`` (world +y up)."""
    elevation, azimuth = np.radians(elevation_deg), np.radians(azimuth_deg)
    return distance * np.array(
        [np.cos(elevation) * np.sin(azimuth), np.sin(elevation), np.cos(elevation) * np.cos(azimuth)]
    )


def paper_rig() -> Rig:
    """The seed paper's synthetic set-up, pixel for pixel what PyTorch3D renders.

    PyTorch3D's view frame (+X left, +Y up, +Z forward) is the dsareg view frame
    turned 180° about z, so ``look_at_world_to_view`` with up = +y reproduces it.
    AP: camera at distance 150 mm, elevation 0, azimuth −90° (world −x), looking at the
    origin; LAT: 90° further in azimuth (the paper's W, about +y). The mesh frame is the
    world frame at the true pose; the initial pose is the paper's perturbed AP camera.
    """
    focal = paper_focal_px()
    views = {}
    for name, azimuth in (("ap", -90.0), ("lat", 0.0)):
        eye = pytorch3d_camera_position(PAPER_CAMERA_DISTANCE_MM, 0.0, azimuth)
        views[name] = ViewGeometry(
            image_size=(PAPER_IMAGE_SIZE, PAPER_IMAGE_SIZE),
            pixel_spacing_mm=(PAPER_PIXEL_SPACING_MM, PAPER_PIXEL_SPACING_MM),
            sid_mm=focal * PAPER_PIXEL_SPACING_MM,
            principal_point_px=default_principal_point((PAPER_IMAGE_SIZE, PAPER_IMAGE_SIZE)),
            world_to_view=look_at_world_to_view(eye, np.zeros(3), np.array([0.0, 1.0, 0.0])),
        )
    return Rig(views=views, initial_mesh_to_world=paper_initial_mesh_to_world(views["ap"]))


def paper_initial_mesh_to_world(ap_view: ViewGeometry) -> np.ndarray:
    """The paper's starting pose: AP camera at [-150, 10, -30] looking at [10, 0, 5], up +y.

    The camera is given in mesh coordinates, i.e. it defines ``mesh_to_view``; the
    corresponding ``mesh_to_world`` is ``view_to_world · mesh_to_view``.
    """
    mesh_to_view = look_at_world_to_view(np.array([-150.0, 10.0, -30.0]), np.array([10.0, 0.0, 5.0]), np.array([0.0, 1.0, 0.0]))
    return invert_rigid(ap_view.world_to_view) @ mesh_to_view


PRESETS = {"paper": paper_rig}
"""Named rigs accepted wherever a geometry is asked for."""
