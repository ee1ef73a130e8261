"""A vessel model's length unit: which one the file is in, its scale to millimetres, and a size check.

Every coordinate inside dsareg is in millimetres. A mesh file states no unit except glTF/GLB, whose
specification fixes the metre; the other formats (OBJ, STL, PLY, OFF) are read in millimetres unless
``options.mesh_units`` says otherwise (``mm``, ``cm``, ``m``). The option, when given, wins over the
format's own unit (some exporters write millimetres into a GLB regardless of its specification).

A unit mistake shows as a size no head artery tree has: a tree in metres read as millimetres is a
tenth of a millimetre across, one in millimetres read as centimetres is a metre. The model's largest
extent (axis-aligned box, mm, after the unit) must lie in :data:`PLAUSIBLE_EXTENT_MM`; outside it the
model is refused with the extent, the unit assumed and what to do. The unit taken is recorded as an
:class:`~.input_decisions.InputDecision`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import DsaregInputError
from ..mesh import TriangleMesh
from .input_decisions import InputDecision

MM_PER_UNIT = {"mm": 1.0, "cm": 10.0, "m": 1000.0}
"""Millimetres in one of each accepted unit."""

MESH_UNITS = tuple(MM_PER_UNIT)

FORMAT_UNITS = {"glb": "m"}
"""Formats whose specification fixes the unit (glTF 2.0: metres); the others carry none (read as mm)."""


@dataclass(frozen=True)
class ExtentRange:
    """Largest extents (mm) a vessel model of the head can have.

    Attributes:
        low_mm: below this the model is smaller than a trimmed carotid segment (a model in cm or m read as mm).
        high_mm: above this it is larger than a head (a model in mm read as cm or m).
        band_fraction: a measured unit whose extent lies within this fraction of the upper limit is a close call.
        low_close_mm: a measured unit whose extent lies below this is a close call: a body model in cm read as mm
            lands here (SimVascular's 34.5-cm aorto-iliac tree reads 34.5 mm), and so does a small head crop in
            mm; size alone cannot tell them apart (nor can the vessels' calibre), so the verdict is at most
            ``check`` until the unit is stated.
    """

    low_mm: float = 15.0
    high_mm: float = 400.0
    band_fraction: float = 0.2
    low_close_mm: float = 37.5


PLAUSIBLE_EXTENT_MM = ExtentRange()


@dataclass(frozen=True)
class MeshUnit:
    """The unit a model was read in.

    Attributes:
        unit: ``"mm"``, ``"cm"`` or ``"m"``.
        source: ``"option"`` (options.mesh_units), ``"tag"`` (the format's specification) or ``"measured"``
            (no unit stated: millimetres, checked by the model's size).
    """

    unit: str
    source: str

    @property
    def scale_mm(self) -> float:
        """Millimetres per file unit."""
        return MM_PER_UNIT[self.unit]


def check_unit_name(unit: str | None, field_name: str = "options.mesh_units") -> str | None:
    """``unit`` when it is one of :data:`MESH_UNITS` (or None); a clear error otherwise."""
    if unit is None or unit in MM_PER_UNIT:
        return unit
    raise DsaregInputError(f"unknown unit '{unit}'", field=field_name, accepted=", ".join(MESH_UNITS))


def mesh_unit(fmt: str, option: str | None) -> MeshUnit:
    """The unit of a mesh of format ``fmt``: the option when given, else the format's own, else millimetres."""
    if check_unit_name(option) is not None:
        return MeshUnit(option, "option")
    if fmt in FORMAT_UNITS:
        return MeshUnit(FORMAT_UNITS[fmt], "tag")
    return MeshUnit("mm", "measured")


def largest_extent_mm(vertices: np.ndarray) -> float:
    """The largest side of the axis-aligned box of ``vertices`` ``(N, 3)`` mm."""
    return float(np.ptp(np.asarray(vertices, float), axis=0).max())


def unit_decision(mesh: TriangleMesh, unit: MeshUnit, field_name: str = "mesh",
                  limits: ExtentRange = PLAUSIBLE_EXTENT_MM) -> InputDecision:
    """Check the model's size in mm (read in ``unit``) and record the unit as a decision.

    Raises:
        DsaregInputError: the largest extent is outside ``limits`` (naming ``field_name``, the extent in mm,
            the unit assumed and the option that states another).
    """
    extent = largest_extent_mm(mesh.vertices)
    if not limits.low_mm <= extent <= limits.high_mm:
        raise DsaregInputError(_implausible_message(extent, unit, field_name, limits), field=field_name,
                               accepted=_accepted(extent, unit, field_name, limits))
    low = extent < np.sqrt(limits.low_mm * limits.high_mm)
    nearest = limits.low_mm if low else limits.high_mm
    band = limits.low_close_mm - limits.low_mm if low else limits.band_fraction * nearest
    return InputDecision(input=field_name, what="units", chosen=unit.unit,
                         basis="the model's largest extent in mm (small: a body model in cm read as mm?)" if low
                         else "the model's largest extent in mm", measure=round(extent, 3), threshold=nearest,
                         band=band, source=unit.source)


def _how_read(unit: MeshUnit, field_name: str) -> str:
    if field_name != "mesh":
        return "in mm from its voxel spacing"
    return {"option": f"in {unit.unit} as options.mesh_units says",
            "tag": f"in {unit.unit} as its format's specification says"}.get(unit.source, f"in {unit.unit} (the "
                                                                                           "format states no unit)")


def _implausible_message(extent: float, unit: MeshUnit, field_name: str, limits: ExtentRange) -> str:
    side = "small" if extent < limits.low_mm else "large"
    return (f"the model is {extent:.3g} mm across read {_how_read(unit, field_name)}: too {side} for head arteries "
            f"({limits.low_mm:.0f} to {limits.high_mm:.0f} mm); its unit is probably not {unit.unit}")


def _accepted(extent: float, unit: MeshUnit, field_name: str, limits: ExtentRange) -> str:
    if field_name != "mesh":
        return (f"a volume whose vessels span {limits.low_mm:.0f} to {limits.high_mm:.0f} mm (check the voxel "
                "spacing in its header)")
    fits = [name for name, scale in MM_PER_UNIT.items()
            if limits.low_mm <= extent / unit.scale_mm * scale <= limits.high_mm and name != unit.unit]
    hint = f" (here probably {' or '.join(fits)})" if fits else ""
    return (f"a model of head arteries; state its unit with options.mesh_units (on the command line --mesh-units): "
            f"mm, cm or m{hint}")
