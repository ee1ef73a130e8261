"""Surface meshes from bytes: OBJ, STL (ASCII and binary), PLY, OFF, GLB, VTP and legacy VTK polydata.

Nothing here touches the filesystem: the bytes are parsed by trimesh from memory with
no resolver, so ``mtllib`` and texture references are never followed; ``.vtp`` and legacy ``.vtk`` surfaces (VMTK,
SimVascular, CFD models) by VTK's own readers, from memory too (:mod:`.vtk_polydata`). The format is
detected from the content; the file name's extension is only a hint (a warning says
when it disagrees). Coordinates are scaled to millimetres from the file's unit: glTF/GLB's metre,
millimetres for the formats that state none, or the unit the caller gives (:mod:`.mesh_units`).

Meshes larger than ``limits.working_faces`` are decimated with quadric error
simplification (fast-simplification, through trimesh), which keeps thin tubes: its
error metric weighs distance to the original surface, so a thin vessel is never
collapsed while flat, well-sampled regions can absorb the reduction. Where that
package is missing, vertex clustering on a fine grid is used instead.
"""

from __future__ import annotations

import io
import logging
import re
import struct
import warnings as _warnings
from dataclasses import dataclass, field

import numpy as np

from ..errors import DsaregInputError
from ..mesh import (  # noqa: F401 - decimate and _cluster_decimate re-exported (their home is ..mesh)
    MESH_FILES_ACCEPTED,
    TriangleMesh,
    _cluster_decimate,
    decimate,
    mesh_from_arrays,
)
from .limits import DEFAULT_LIMITS, InputLimits
from .mesh_limits import check_mesh_bytes
from .mesh_units import MeshUnit, mesh_unit
from .vtk_polydata import VTK_MESH_FORMATS, declared_triangles, detect_vtk_polydata, legacy_dataset, parse_vtk_polydata

log = logging.getLogger(__name__)

MESH_FORMATS = ("obj", "stl", "ply", "off", "glb") + VTK_MESH_FORMATS
_ACCEPTED = MESH_FILES_ACCEPTED


@dataclass
class MeshReadResult:
    """A mesh and what happened while reading it."""

    mesh: TriangleMesh
    format: str
    original_faces: int
    warnings: list[str] = field(default_factory=list)
    unit: MeshUnit = MeshUnit("mm", "measured")
    """The unit the file was read in (its coordinates were multiplied by ``unit.scale_mm``)."""


def detect_mesh_format(data: bytes) -> str | None:
    """The mesh format the bytes look like, or ``None``."""
    head = data[:512]
    if head[:4] == b"glTF":
        return "glb"
    if head[:3].lower() == b"ply":
        return "ply"
    vtk = detect_vtk_polydata(data)
    if vtk is not None:
        return vtk
    if len(data) >= 84:
        (n_faces,) = struct.unpack_from("<I", data, 80)
        if len(data) == 84 + 50 * n_faces and n_faces > 0:
            return "stl"
    stripped = head.lstrip()
    if re.match(rb"^[A-Z]{0,4}OFF\b", stripped[:12]):
        return "off"
    if stripped[:5].lower() == b"solid" and b"facet" in data[:65536].lower():
        return "stl"
    if b"\x00" in head:
        return None
    if re.search(rb"(?m)^\s*v\s+[-+.\d]", data[: 1 << 20]) and re.search(rb"(?m)^\s*f\s+\d", data):
        return "obj"
    return None


def _is_binary_stl(data: bytes) -> bool:
    """Binary unless it starts with ``solid`` and is not exactly the size a binary STL would be."""
    if len(data) >= 84 and len(data) == 84 + 50 * struct.unpack_from("<I", data, 80)[0]:
        return True
    return data.lstrip()[:5].lower() != b"solid"


def _pillow_bomb_warning() -> type[Warning]:
    try:
        from PIL import Image

        return Image.DecompressionBombWarning
    except ImportError:  # pragma: no cover
        return RuntimeWarning


def _declared_faces(data: bytes, fmt: str) -> int | None:
    """Face count stated by the header (checked against the ceiling before parsing)."""
    if fmt == "stl" and len(data) >= 84 and _is_binary_stl(data):
        return struct.unpack_from("<I", data, 80)[0]
    if fmt == "stl":
        return data.lower().count(b"facet normal")
    if fmt == "ply":
        match = re.search(rb"element\s+face\s+(\d+)", data[:65536])
        return int(match.group(1)) if match else None
    if fmt == "off":
        text = re.sub(rb"#[^\n]*", b"", data[:65536]).lstrip()
        numbers = re.sub(rb"^[A-Z]*OFF", b"", text).split()[:3]
        try:
            return int(numbers[1])
        except (IndexError, ValueError):
            return None
    if fmt == "obj":
        return len(re.findall(rb"(?m)^\s*f\s", data))
    if fmt in VTK_MESH_FORMATS:
        return declared_triangles(data, fmt)
    return None


def read_mesh(data: bytes, filename: str | None = None, limits: InputLimits = DEFAULT_LIMITS) -> TriangleMesh:
    """Read a mesh from bytes (see :func:`read_mesh_detailed`)."""
    return read_mesh_detailed(data, filename, limits).mesh


def read_mesh_detailed(
    data: bytes, filename: str | None = None, limits: InputLimits = DEFAULT_LIMITS, *, field_name: str = "mesh",
    units: str | None = None,
) -> MeshReadResult:
    """Parse, validate and (above the working budget) decimate a mesh, in mm.

    ``units``: the file's unit (``mm``, ``cm``, ``m``); ``None``: the format's own (GLB: metres), else mm.

    Raises:
        DsaregInputError: empty/truncated/unknown data, non-finite vertices, no faces,
            face indices out of range, more than ``limits.max_faces`` faces.
    """
    if not data:
        raise DsaregInputError("the file is empty", field=field_name, accepted=_ACCEPTED)
    warnings: list[str] = []
    extension = filename.rsplit(".", 1)[-1].lower() if filename and "." in filename else None
    fmt = detect_mesh_format(data)
    if fmt is None and legacy_dataset(data):
        raise DsaregInputError(f"is a legacy VTK {legacy_dataset(data)} file, not a surface", field=field_name,
                               accepted=f"{_ACCEPTED}; a VTK image volume goes in as the volume, not the mesh")
    if fmt is None:
        if extension in MESH_FORMATS:
            fmt = extension  # let the parser say what is wrong with it
        else:
            raise DsaregInputError("content is not a recognised mesh format", field=field_name, accepted=_ACCEPTED)
    elif extension is not None and extension != fmt:
        warnings.append(
            f"{field_name}: the file is named '.{extension}' but its content is {fmt.upper()}; read as {fmt.upper()}"
        )
    check_mesh_bytes(data, fmt, limits, field_name)  # vertices, faces, a GLB's structure: before parsing
    declared = _declared_faces(data, fmt)
    if declared is not None and declared > limits.max_faces:
        raise DsaregInputError(
            f"declares {declared} faces, above the limit of {limits.max_faces}",
            field=field_name,
            accepted=f"at most {limits.max_faces} faces (decimate it first)",
        )
    unit = mesh_unit(fmt, units)
    vertices, faces = _parse(data, fmt, field_name)
    vertices = vertices * unit.scale_mm
    mesh = validate_mesh_arrays(vertices, faces, limits, field_name=field_name)
    original = mesh.n_faces
    if original > limits.working_faces:
        mesh = decimate(mesh, limits.working_faces)
        warnings.append(
            f"{field_name}: decimated from {original} to {mesh.n_faces} faces (working budget {limits.working_faces})"
        )
    return MeshReadResult(mesh=mesh, format=fmt, original_faces=original, warnings=warnings, unit=unit)


# an ``f`` line with a vertex reference ``0`` (``0``, ``0/…``): OBJ indices are 1-based
_OBJ_ZERO_INDEX = re.compile(rb"(?m)^[ \t]*f(?:[ \t]+\S+)*?[ \t]+[+]?0+(?:/\S*)?(?=[ \t]*$|[ \t\r])")


def _parse(data: bytes, fmt: str, field_name: str) -> tuple[np.ndarray, np.ndarray]:
    import trimesh

    if fmt in VTK_MESH_FORMATS:
        return parse_vtk_polydata(data, fmt, field_name)
    if fmt == "stl" and _is_binary_stl(data):
        (n_faces,) = struct.unpack_from("<I", data, 80) if len(data) >= 84 else (None,)
        if n_faces is None or len(data) < 84 + 50 * n_faces:
            raise DsaregInputError(
                f"binary STL is truncated ({len(data)} bytes, {n_faces} faces declared)", field=field_name
            )
    if fmt == "obj":
        # Never follow material or texture references.
        data = re.sub(rb"(?m)^\s*(mtllib|usemtl)\b.*$", b"", data)
        zero = _OBJ_ZERO_INDEX.search(data)
        if zero is not None:  # trimesh would turn index 0 into -1, i.e. silently the last vertex
            line = data.count(b"\n", 0, zero.start()) + 1
            raise DsaregInputError(f"face on line {line} uses vertex index 0; OBJ indices start at 1",
                                   field=field_name, accepted="OBJ faces with indices 1..n (or negative, relative)")
    try:
        with _warnings.catch_warnings():
            _warnings.simplefilter("ignore")
            # embedded textures (GLB) are decoded by Pillow: a decompression bomb there is an error
            _warnings.simplefilter("error", _pillow_bomb_warning())
            loaded = trimesh.load(file_obj=io.BytesIO(data), file_type=fmt, force="mesh", process=False, resolver=None)
    except DsaregInputError:
        raise
    except Exception as exc:  # trimesh raises many types on malformed data
        raise DsaregInputError(
            f"could not be parsed as {fmt.upper()} ({type(exc).__name__}: {str(exc)[:200]})",
            field=field_name,
            accepted=_ACCEPTED,
        ) from None
    vertices = np.asarray(getattr(loaded, "vertices", np.zeros((0, 3))), dtype=np.float64)
    faces = np.asarray(getattr(loaded, "faces", np.zeros((0, 3))))
    return vertices, faces


def validate_mesh_arrays(
    vertices: np.ndarray, faces: np.ndarray, limits: InputLimits = DEFAULT_LIMITS, *, field_name: str = "mesh"
) -> TriangleMesh:
    """Check raw arrays and return a clean :class:`TriangleMesh` (duplicate vertices merged)."""
    return mesh_from_arrays(vertices, faces, max_faces=limits.max_faces, field_name=field_name)
