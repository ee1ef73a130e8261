"""The geometry of a case as one typed value: parsed and validated once, stored in one canonical form.

:func:`parse_geometry` is the only place that decides what a geometry argument is: a preset
name, JSON text (``str`` or UTF-8 ``bytes``), an already-parsed JSON object, or — for the
command line only (``files=True``) — the path of a JSON file. It returns a
:class:`GeometrySpec`: the validated :class:`~dsareg_engine.geometry.rig.Rig` and where it came from.

:meth:`GeometrySpec.to_json` writes the canonical form, always the explicit views (a preset, a
``projection_matrix`` or ``lat_from_ap`` expanded); the preset name is kept as provenance only::

    {"format": "dsareg.geometry/1",
     "views": {"ap": {"image_size": [W, H], "pixel_spacing_mm": [du, dv], "sid_mm": ...,
                      "principal_point_px": [u0, v0], "world_to_view": 4x4},
               "lat": {...}},
     "initial_mesh_to_world": 4x4 or null,
     "provenance": {"source": "preset" | "json" | "file", "preset": "paper" | null}}

:meth:`GeometrySpec.from_json` reads exactly that form back and nothing else: no preset lookup,
no guessing. Floats survive the round trip bit for bit (``json`` writes ``repr``).
"""

from __future__ import annotations

import json
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, PositiveFloat, PositiveInt, ValidationError

from ..errors import DsaregInputError
from .rig import Rig, ViewGeometry
from .file import PRESETS, rig_from_dict

GEOMETRY_FORMAT = "dsareg.geometry/1"
"""Version tag of the canonical form; the first member of every canonical text."""

CANONICAL_PREFIX = '{"format":"' + GEOMETRY_FORMAT + '"'
"""How every text written by :meth:`GeometrySpec.to_json` starts."""

Source = Literal["preset", "json", "file"]


def accepted_inputs(files: bool = False) -> str:
    """What a geometry argument may be (for error messages)."""
    kinds = f"a preset name {sorted(PRESETS)}, " + ("a geometry JSON file, " if files else "")
    return kinds + "or a JSON object {'views': {'ap': {...}, 'lat': {...}}, 'initial_mesh_to_world': 4x4}"


@dataclass(frozen=True)
class GeometrySpec:
    """A validated geometry.

    Attributes:
        rig: the views (explicit: image size, spacing, SID, principal point, ``world_to_view``)
            and the initial pose (``rig.initial_pose_given`` false when none was given).
        source: what the argument was: ``"preset"``, ``"json"`` (text or object) or ``"file"``.
        preset: the preset's name when ``source == "preset"`` (provenance only: loading never
            looks it up again).
    """

    rig: Rig
    source: Source
    preset: str | None = None

    def to_dict(self) -> dict[str, Any]:
        """The canonical form as a JSON-ready dict (see the module docstring)."""
        rig = self.rig
        return {
            "format": GEOMETRY_FORMAT,
            "views": {name: view.to_dict() for name, view in rig.views.items()},
            "initial_mesh_to_world": rig.initial_mesh_to_world.tolist() if rig.initial_pose_given else None,
            "provenance": {"source": self.source, "preset": self.preset},
        }

    def to_json(self) -> str:
        """The canonical text (compact; starts with :data:`CANONICAL_PREFIX`)."""
        return json.dumps(self.to_dict(), separators=(",", ":"))

    def as_input(self) -> str | dict[str, Any]:
        """What to hand another dsareg (``dsareg submit``): the preset's name, or the explicit geometry file."""
        return self.preset if self.source == "preset" and self.preset else self.rig.to_dict()

    @classmethod
    def from_json(cls, text: str | bytes) -> GeometrySpec:
        """Read the canonical form written by :meth:`to_json` (anything else is refused)."""
        try:
            stored = _Canonical.model_validate_json(text)
        except ValidationError as exc:
            first = exc.errors()[0]
            where = ".".join(str(part) for part in first["loc"])
            raise DsaregInputError(f"stored geometry is not in the canonical form: {first['msg']}",
                                   field=f"geometry.{where}" if where else "geometry",
                                   accepted=f"the output of GeometrySpec.to_json ({GEOMETRY_FORMAT})") from None
        views = {name: ViewGeometry(image_size=view.image_size, pixel_spacing_mm=view.pixel_spacing_mm,
                                    sid_mm=view.sid_mm, principal_point_px=view.principal_point_px,
                                    world_to_view=np.asarray(view.world_to_view, dtype=np.float64))
                 for name, view in stored.views.items()}
        pose = None if stored.initial_mesh_to_world is None else np.asarray(stored.initial_mesh_to_world, np.float64)
        return cls(Rig(views=views, initial_mesh_to_world=pose), stored.provenance.source, stored.provenance.preset)


def is_canonical_geometry(text: str) -> bool:
    """Whether ``text`` was written by :meth:`GeometrySpec.to_json` (checks the version tag only)."""
    return text.startswith(CANONICAL_PREFIX)


# ---- the canonical form's schema (for loading) ------------------------------------------------

Matrix = list[list[float]]


class _ExplicitView(BaseModel):
    model_config = ConfigDict(extra="forbid")
    image_size: tuple[PositiveInt, PositiveInt]
    pixel_spacing_mm: tuple[PositiveFloat, PositiveFloat]
    sid_mm: PositiveFloat
    principal_point_px: tuple[float, float]
    world_to_view: Matrix


class _Provenance(BaseModel):
    model_config = ConfigDict(extra="forbid")
    source: Source
    preset: str | None = None


class _Canonical(BaseModel):
    model_config = ConfigDict(extra="forbid")
    format: Literal["dsareg.geometry/1"]
    views: dict[Literal["ap", "lat"], _ExplicitView]
    initial_mesh_to_world: Matrix | None
    provenance: _Provenance


# ---- parsing what a person or a client gave ----------------------------------------------------


def parse_geometry(value: str | bytes | Mapping[str, Any], *, field: str = "geometry", files: bool = False,
                   loads: Callable[[str], Any] = json.loads) -> GeometrySpec:
    """Decide what ``value`` is, once, and validate it into a :class:`GeometrySpec`.

    Args:
        value: a preset name, JSON object text (``str`` or UTF-8 ``bytes``), or a parsed JSON object.
        field: the argument's name in error messages (``"geometry"``, ``"--geometry"``).
        files: also accept the path of a JSON file (the command line; never a server, which
            must not read its own files on a client's behalf).
        loads: the JSON parser (the service passes its depth- and number-bounded one).

    Raises:
        DsaregInputError: naming the field at fault (``geometry.views.ap.sid_mm``...) and what is accepted.
    """
    if isinstance(value, Mapping):
        return GeometrySpec(rig_from_dict(dict(value)), "json")
    text = _text(value, field, files)
    if text in PRESETS:
        return GeometrySpec(PRESETS[text](), "preset", text)
    if text.startswith("{"):
        return GeometrySpec(rig_from_dict(_json_object(text, field, files, loads)), "json")
    if files:
        return GeometrySpec(rig_from_dict(_json_object(_read_file(text, field), field, files, loads)), "file")
    raise DsaregInputError(f"'{text[:60]}' is neither a preset nor JSON", field=field,
                           accepted=accepted_inputs(files))


def _text(value: Any, field: str, files: bool) -> str:
    if isinstance(value, (bytes, bytearray)):
        try:
            value = bytes(value).decode("utf-8")
        except UnicodeDecodeError:
            raise DsaregInputError("is not UTF-8 text", field=field, accepted=accepted_inputs(files)) from None
    if not isinstance(value, str):
        raise DsaregInputError(f"has type {type(value).__name__}", field=field, accepted=accepted_inputs(files))
    text = value.strip()
    if not text:
        raise DsaregInputError("is empty", field=field, accepted=accepted_inputs(files))
    return text


def _json_object(text: str, field: str, files: bool, loads: Callable[[str], Any]) -> dict[str, Any]:
    try:
        data = loads(text)
    except json.JSONDecodeError as exc:
        raise DsaregInputError(f"is not valid JSON ({exc.msg} at line {exc.lineno} column {exc.colno})",
                               field=field, accepted=accepted_inputs(files)) from None
    if not isinstance(data, dict):
        raise DsaregInputError(f"is JSON {type(data).__name__}, not an object", field=field,
                               accepted=accepted_inputs(files))
    return data


def _read_file(text: str, field: str) -> str:
    path = Path(text).expanduser()
    if path.is_file():
        return path.read_text(encoding="utf-8", errors="replace")
    if path.exists():
        raise DsaregInputError(f"'{text}' is a folder, not a geometry file", field=field,
                               accepted=accepted_inputs(True))
    raise DsaregInputError(f"geometry file '{text}' not found", field=field, accepted=accepted_inputs(True))


def load_rig(source: str | Path | Mapping[str, Any]) -> Rig:
    """A rig from a preset name, a JSON file path, JSON text, or a parsed object (scripts and tests:
    :func:`parse_geometry` with files allowed)."""
    return parse_geometry(str(source) if isinstance(source, Path) else source, files=True).rig
