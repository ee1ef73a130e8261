"""The field of view of an X-ray image from its DICOM Shutter and X-Ray Collimator modules.

A C-arm's detector sees the patient only inside the collimator's opening (often round, or a
rectangle); outside, the image is black (or, after MONOCHROME1 inversion, white) and its edge is
sharp. The file says where that opening is:

* **Display Shutter** (PS3.3 C.7.6.11), Shutter Shape (0018,1600), one or more of
  ``RECTANGULAR`` (left / right vertical edges (0018,1602) / (0018,1604), columns; upper / lower
  horizontal edges (0018,1606) / (0018,1608), rows), ``CIRCULAR`` (Center of Circular Shutter
  (0018,1610) row\\column, Radius (0018,1612) px), ``POLYGONAL`` (Vertices (0018,1620) row\\column
  pairs) and ``BITMAP`` (Shutter Overlay Group (0018,1623): the overlay plane 60xx whose set bits
  are the shuttered area).
* **X-Ray Collimator** (C.8.7.3), Collimator Shape (0018,1700): ``RECTANGULAR`` (0018,1702..1708),
  ``CIRCULAR`` (0018,1710, 0018,1712), ``POLYGONAL`` (0018,1720); enhanced XA stores it in the
  functional groups (read from the frame used).

Coordinates are DICOM's: 1-based rows and columns, the first pixel's centre at (1, 1). The field
of view is where every shape given lets the beam through (their intersection); ``True`` inside.
A shape that cannot be applied (values missing or not numbers, an empty opening) is left out
with a warning: these modules are display aids, not a reason to refuse an image.

Overlay planes (60xx,3000) other than a bitmap shutter's are graphics drawn over the image on
display (annotations, markers); :func:`overlay_annotation_mask` gathers those of type ``G``.
"""

from __future__ import annotations

import cv2
import numpy as np

SHAPES = ("RECTANGULAR", "CIRCULAR", "POLYGONAL", "BITMAP")
SHUTTER_TAGS = {"edges": ("ShutterLeftVerticalEdge", "ShutterRightVerticalEdge", "ShutterUpperHorizontalEdge",
                          "ShutterLowerHorizontalEdge"),
                "centre": "CenterOfCircularShutter", "radius": "RadiusOfCircularShutter",
                "vertices": "VerticesOfThePolygonalShutter"}
COLLIMATOR_TAGS = {"edges": ("CollimatorLeftVerticalEdge", "CollimatorRightVerticalEdge",
                             "CollimatorUpperHorizontalEdge", "CollimatorLowerHorizontalEdge"),
                   "centre": "CenterOfCircularCollimator", "radius": "RadiusOfCircularCollimator",
                   "vertices": "VerticesOfThePolygonalCollimator"}


def _value(dataset, keyword: str, frame: int | None):
    from .dicom_xa import find_tag

    try:
        return find_tag(dataset, keyword, frame)
    except Exception:  # noqa: BLE001 - a malformed value reads as absent
        return None


def _numbers(value) -> list[float] | None:
    if value is None:
        return None
    iterable = hasattr(value, "__iter__") and not isinstance(value, (str, bytes))
    values = list(value) if iterable else [value]
    try:
        numbers = [float(v) for v in values]
    except (TypeError, ValueError):
        return None
    return numbers if numbers and all(np.isfinite(numbers)) else None


def _shapes(value) -> list[str]:
    if value is None:
        return []
    values = [value] if isinstance(value, str) else list(value)
    return [str(v).strip().upper() for v in values if str(v).strip()]


def _rectangle(dataset, tags, frame, shape_rc) -> np.ndarray | None:
    edges = [_numbers(_value(dataset, keyword, frame)) for keyword in tags["edges"]]
    if any(edge is None for edge in edges):
        return None
    left, right, upper, lower = (edge[0] - 1.0 for edge in edges)  # 0-based
    rows, columns = np.arange(shape_rc[0])[:, None], np.arange(shape_rc[1])[None, :]
    return (columns >= left) & (columns <= right) & (rows >= upper) & (rows <= lower)


def _circle(dataset, tags, frame, shape_rc) -> np.ndarray | None:
    centre, radius = _numbers(_value(dataset, tags["centre"], frame)), _numbers(_value(dataset, tags["radius"], frame))
    if centre is None or radius is None or len(centre) != 2 or radius[0] <= 0:
        return None
    rows, columns = np.arange(shape_rc[0])[:, None], np.arange(shape_rc[1])[None, :]
    return (rows - (centre[0] - 1.0)) ** 2 + (columns - (centre[1] - 1.0)) ** 2 <= radius[0] ** 2


def _polygon(dataset, tags, frame, shape_rc) -> np.ndarray | None:
    vertices = _numbers(_value(dataset, tags["vertices"], frame))
    if vertices is None or len(vertices) < 6 or len(vertices) % 2:
        return None
    points = np.array([[column - 1.0, row - 1.0] for row, column in zip(vertices[::2], vertices[1::2])])
    inside = np.zeros(shape_rc, np.uint8)
    cv2.fillPoly(inside, [np.round(points * 16).astype(np.int32)], 1, lineType=cv2.LINE_8, shift=4)
    return inside.astype(bool)


def overlay_plane(dataset, group: int, shape_rc: tuple[int, int]) -> np.ndarray | None:
    """Overlay plane ``group`` (0x6000..0x601E) as a bool ``shape_rc`` array placed at its Overlay Origin; None
    when it is absent or unreadable."""
    if (group, 0x3000) not in dataset:
        return None
    try:
        bits = np.asarray(dataset.overlay_array(group), dtype=bool)
        if bits.ndim == 3:
            bits = bits[0]
        origin = dataset.get((group, 0x0050))
        row0, column0 = (int(v) - 1 for v in origin.value) if origin is not None else (0, 0)
    except Exception:  # noqa: BLE001 - a malformed overlay is left out
        return None
    plane = np.zeros(shape_rc, bool)
    top, left = max(row0, 0), max(column0, 0)
    bottom, right = min(row0 + bits.shape[0], shape_rc[0]), min(column0 + bits.shape[1], shape_rc[1])
    if bottom > top and right > left:
        plane[top:bottom, left:right] = bits[top - row0:bottom - row0, left - column0:right - column0]
    return plane


def _bitmap(dataset, frame, shape_rc) -> np.ndarray | None:
    group = _numbers(_value(dataset, "ShutterOverlayGroup", frame))
    if group is None:
        return None
    plane = overlay_plane(dataset, int(group[0]), shape_rc)
    return None if plane is None else ~plane


_MAKERS = {"RECTANGULAR": _rectangle, "CIRCULAR": _circle, "POLYGONAL": _polygon}


def field_of_view_details(dataset, shape_rc: tuple[int, int], frame: int | None = None
                          ) -> tuple[np.ndarray | None, list[str], list[str]]:
    """``(field of view or None, the shapes applied (e.g. "shutter CIRCULAR"), warnings)``."""
    openings, applied, warnings = [], [], []
    for module, keyword, tags in (("shutter", "ShutterShape", SHUTTER_TAGS),
                                  ("collimator", "CollimatorShape", COLLIMATOR_TAGS)):
        for shape in _shapes(_value(dataset, keyword, frame)):
            if shape == "BITMAP" and module == "shutter":
                opening = _bitmap(dataset, frame, shape_rc)
            elif shape in _MAKERS:
                opening = _MAKERS[shape](dataset, tags, frame, shape_rc)
            else:
                warnings.append(f"{module} shape '{shape[:16]}' is not one of {', '.join(SHAPES)}; left out")
                continue
            if opening is None or not opening.any():
                warnings.append(f"the {module}'s {shape} opening is incomplete or empty in the file; left out")
                continue
            openings.append(opening)
            applied.append(f"{module} {shape}")
    if not openings:
        return None, applied, warnings
    return np.logical_and.reduce(openings), applied, warnings


def shutter_field_of_view(dataset, shape_rc: tuple[int, int], frame: int | None = None) -> np.ndarray | None:
    """Bool ``shape_rc`` (rows, columns): ``True`` where the detector sees the patient, from the Shutter and
    Collimator modules of ``dataset`` (a pydicom Dataset); None when the file has neither (or none applies)."""
    return field_of_view_details(dataset, shape_rc, frame)[0]


def overlay_annotation_mask(dataset, shape_rc: tuple[int, int]) -> np.ndarray | None:
    """The union of the graphics overlay planes (type ``G``; not a bitmap shutter's plane): annotations drawn
    over the image; None when there are none."""
    shutter_group = _numbers(_value(dataset, "ShutterOverlayGroup", None))
    found = None
    for group in range(0x6000, 0x6020, 2):
        if shutter_group is not None and group == int(shutter_group[0]):
            continue
        kind = dataset.get((group, 0x0040))
        if kind is not None and str(kind.value).strip().upper() not in ("G", ""):
            continue
        plane = overlay_plane(dataset, group, shape_rc)
        if plane is not None and plane.any():
            found = plane if found is None else found | plane
    return found
