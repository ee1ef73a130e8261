"""Imaging geometry from DICOM XA headers (single-frame, multi-frame and enhanced XA).

Only geometry tags are read; nothing identifying the patient is logged or kept.

**Frames.** World origin = the isocentre; world axes = patient LPS (+x Left,
+y Posterior, +z Superior), mm.

**C-arm angles** (DICOM PS3.3 C.8.7.5): ``PositionerPrimaryAngle`` α is the rotation
about the patient's head-foot axis, LAO positive (the detector moves toward the
patient's left); ``PositionerSecondaryAngle`` β tilts the beam toward the head,
CRA positive. At α = β = 0 (AP) the source is posterior and the detector anterior,
so the central ray (source → detector) points anterior (−y). In general the unit
vector from isocentre toward the detector is::

    d = (cos β sin α, −cos β cos α, sin β)

i.e. the imaging chain is turned by ``R = Rz(α) · Rx(−β)`` from its AP position.

**Image axes.** At AP the image is stored as seen on the monitor: columns increase
toward the patient's left, rows toward the feet (head up). The image axes turn with
the chain: view x = R·(1, 0, 0), view y = R·(0, 0, −1), view z = d. This frame is
mirrored (det −1) with respect to LPS, which :class:`ViewGeometry` allows. A system
that stores images flipped needs an explicit geometry file instead.

**Distances.** The source sits ``DistanceSourceToPatient`` (source → isocentre) before
the isocentre along −d; ``DistanceSourceToDetector`` is the SID; ``ImagerPixelSpacing``
``[row, column]`` (spacing at the detector) gives ``(du, dv) = (column, row)``; the
principal point is the image centre. If ``ImagerPixelSpacing`` is missing,
``PixelSpacing`` is used (with a warning).
"""

from __future__ import annotations

import io
from dataclasses import dataclass, field

import numpy as np

from ..errors import DsaregInputError
from ..geometry.rig import Rig, ViewGeometry, default_principal_point
from ..geometry.pose import make_transform

GEOMETRY_TAGS = (
    "PositionerPrimaryAngle",
    "PositionerSecondaryAngle",
    "DistanceSourceToDetector",
    "DistanceSourceToPatient",
    "ImagerPixelSpacing",
)


@dataclass
class XaGeometry:
    """The geometry tags of one XA instance (no identifiers)."""

    primary_deg: float
    secondary_deg: float
    sid_mm: float
    sod_mm: float
    pixel_spacing_mm: tuple[float, float]  # (du, dv) = (column, row)
    image_size: tuple[int, int]  # (W, H)
    warnings: list[str] = field(default_factory=list)


def find_tag(dataset, keyword: str, frame: int | None = None):
    """A tag from the top level, the per-frame or the shared functional groups (nested one level)."""
    if keyword in dataset:
        value = dataset.data_element(keyword).value
        if value is not None and value != "":
            return value
    groups = []
    if "PerFrameFunctionalGroupsSequence" in dataset:
        per_frame = dataset.PerFrameFunctionalGroupsSequence
        index = 0 if frame is None else frame
        if 0 <= index < len(per_frame):
            groups.append(per_frame[index])
    if "SharedFunctionalGroupsSequence" in dataset and len(dataset.SharedFunctionalGroupsSequence):
        groups.append(dataset.SharedFunctionalGroupsSequence[0])
    for group in groups:
        for element in group:
            if element.VR != "SQ":
                continue
            for item in element.value:
                if keyword in item:
                    return item.data_element(keyword).value
                for inner in item:  # one more level (e.g. X-Ray geometry macros)
                    if inner.VR == "SQ":
                        for sub in inner.value:
                            if keyword in sub:
                                return sub.data_element(keyword).value
    return None


def _float(value, keyword: str, field_name: str) -> float:
    try:
        number = float(value)
    except (TypeError, ValueError):
        raise DsaregInputError(f"{keyword} is not a number", field=field_name) from None
    if not np.isfinite(number):
        raise DsaregInputError(f"{keyword} is not finite", field=field_name)
    return number


def xa_geometry(dataset, frame: int | None = None, *, field_name: str = "image") -> XaGeometry | None:
    """The geometry tags of ``dataset`` (a pydicom Dataset), or ``None`` when any is missing."""
    warnings: list[str] = []
    values = {keyword: find_tag(dataset, keyword, frame) for keyword in GEOMETRY_TAGS}
    if values["ImagerPixelSpacing"] is None:
        spacing = find_tag(dataset, "PixelSpacing", frame)
        if spacing is not None:
            values["ImagerPixelSpacing"] = spacing
            warnings.append(f"{field_name}: no ImagerPixelSpacing; PixelSpacing used as the detector spacing")
    if values["DistanceSourceToPatient"] is None:
        iso = find_tag(dataset, "DistanceSourceToIsocenter", frame)
        if iso is not None:
            values["DistanceSourceToPatient"] = iso
    rows, cols = find_tag(dataset, "Rows"), find_tag(dataset, "Columns")
    if any(value is None for value in values.values()) or rows is None or cols is None:
        return None
    spacing = [_float(x, "ImagerPixelSpacing", field_name) for x in values["ImagerPixelSpacing"]]
    if len(spacing) != 2 or min(spacing) <= 0:
        raise DsaregInputError("ImagerPixelSpacing must be two positive numbers", field=field_name)
    sid = _float(values["DistanceSourceToDetector"], "DistanceSourceToDetector", field_name)
    sod = _float(values["DistanceSourceToPatient"], "DistanceSourceToPatient", field_name)
    if not (0 < sod < sid):
        raise DsaregInputError(
            f"DistanceSourceToPatient ({sod} mm) must be positive and below DistanceSourceToDetector ({sid} mm)",
            field=field_name,
        )
    return XaGeometry(
        primary_deg=_float(values["PositionerPrimaryAngle"], "PositionerPrimaryAngle", field_name),
        secondary_deg=_float(values["PositionerSecondaryAngle"], "PositionerSecondaryAngle", field_name),
        sid_mm=sid,
        sod_mm=sod,
        pixel_spacing_mm=(spacing[1], spacing[0]),
        image_size=(int(cols), int(rows)),
        warnings=warnings,
    )


def c_arm_rotation(primary_deg: float, secondary_deg: float) -> np.ndarray:
    """``R = Rz(α) · Rx(−β)``: the imaging chain's rotation from AP (see module docstring)."""
    a, b = np.radians(primary_deg), np.radians(secondary_deg)
    rz = np.array([[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0], [0.0, 0.0, 1.0]])
    rx = np.array([[1.0, 0.0, 0.0], [0.0, np.cos(-b), -np.sin(-b)], [0.0, np.sin(-b), np.cos(-b)]])
    return rz @ rx


AP_VIEW_AXES = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, -1.0, 0.0]]).T
"""Columns: view x, y, z in LPS at AP (0°, 0°)."""


def view_from_angles(
    primary_deg: float,
    secondary_deg: float,
    sid_mm: float,
    sod_mm: float,
    pixel_spacing_mm: tuple[float, float],
    image_size: tuple[int, int],
) -> ViewGeometry:
    """A view from C-arm angles and distances (world = isocentre-centred patient LPS)."""
    axes = c_arm_rotation(primary_deg, secondary_deg) @ AP_VIEW_AXES  # view → world rotation
    source = -sod_mm * axes[:, 2]
    rotation = axes.T
    return ViewGeometry(
        image_size=image_size,
        pixel_spacing_mm=pixel_spacing_mm,
        sid_mm=sid_mm,
        principal_point_px=default_principal_point(image_size),
        world_to_view=make_transform(rotation, -rotation @ source),
    )


def geometry_found(dataset, frame: int | None = None) -> dict:
    """The C-arm geometry tags present (the frame's, else the file's), as numbers: ``{keyword: value}`` (a pixel
    spacing as a list); a value that is not a number is kept as text. What ``inspect`` shows of a geometry that
    is incomplete."""
    found: dict = {}
    for keyword in (*GEOMETRY_TAGS, "PixelSpacing", "DistanceSourceToIsocenter"):
        try:
            value = find_tag(dataset, keyword, frame)
        except Exception:  # noqa: BLE001 - pydicom converts lazily: a malformed value reads as text below
            value = None
        if value is None:
            continue
        try:
            found[keyword] = ([float(v) for v in value] if hasattr(value, "__iter__") and not isinstance(value, str)
                              else float(value))
        except (TypeError, ValueError):
            found[keyword] = str(value)[:40]
    return found


def view_from_xa(
    dataset, frame: int | None = None, *, field_name: str = "image"
) -> tuple[ViewGeometry | None, list[str]]:
    """``(view or None, warnings)`` from an XA dataset; ``None`` when geometry tags are missing."""
    found = xa_geometry(dataset, frame, field_name=field_name)
    if found is None:
        missing = [k for k in GEOMETRY_TAGS if find_tag(dataset, k, frame) is None]
        return None, [f"{field_name}: DICOM lacks geometry tags {missing}"]
    view = view_from_angles(
        found.primary_deg, found.secondary_deg, found.sid_mm, found.sod_mm, found.pixel_spacing_mm, found.image_size
    )
    return view, found.warnings


def rig_from_xa(ap: bytes, lat: bytes) -> Rig:
    """A biplane rig from two XA instances (their true angles, not an assumed 90°)."""
    import pydicom

    views = {}
    for name, data in (("ap", ap), ("lat", lat)):
        try:
            dataset = pydicom.dcmread(io.BytesIO(data), stop_before_pixels=True, force=True)
        except Exception as exc:
            raise DsaregInputError(f"is not readable DICOM ({str(exc)[:200]})", field=name) from None
        view, _ = view_from_xa(dataset, field_name=name)
        if view is None:
            raise DsaregInputError("DICOM carries no C-arm geometry; give a geometry", field=name)
        views[name] = view
    return Rig(views=views)
