"""Mesh inputs bounded by what they cost downstream, checked from the bytes before any parser runs.

:func:`check_mesh_bytes` (called by :func:`.mesh_io.read_mesh_detailed` once the format is known) counts what
a file declares, cheaply (``bytes.count``, header fields, the GLB's JSON chunk), and refuses what a parser
would choke on or what would be carried on at a cost its faces do not justify:

* **vertices** as well as faces: at most :func:`max_vertices` (3 per allowed face), and at most
  :data:`VERTICES_PER_FACE` per face plus :data:`VERTEX_SLACK`: an OBJ of 12k faces and 1 M unused vertices
  is refused here, not turned into a 24 MB review model; an OBJ of 10 M vertex lines is refused in well under
  a second instead of a ``MemoryError`` after 15 s;
* a **GLB**'s structure: its chunks inside the file, every buffer, buffer view and accessor inside what holds
  it (a 2⁴⁰-byte buffer view was an ``AssertionError``), its triangles and vertices (per node that shows a
  mesh) within the limits.

Every refusal is a :class:`~dsareg_engine.errors.DsaregInputError` naming the field, the value and the limit.
:func:`review_bytes` bounds the review page's ``model.json`` (:mod:`.review_files`): a model file whose
document would exceed :data:`REVIEW_MODEL_MAX_BYTES` is shown as the working mesh instead.
"""

from __future__ import annotations

import json
import re
import struct

from ..errors import DsaregInputError
from .limits import InputLimits

VERTICES_PER_FACE = 4
"""More vertices than this per face (``f`` line, polygon) cannot all be used (a quad soup has 4)."""
VERTEX_SLACK = 1024
GLB_MAX_JSON_BYTES = 16 << 20
REVIEW_MODEL_MAX_BYTES = 16 << 20
"""``model.json`` above this (estimated from the file: text ≈ 1 byte of JSON per byte, binary ≈ 2) is not sent."""
_COMPONENT_BYTES = {5120: 1, 5121: 1, 5122: 2, 5123: 2, 5125: 4, 5126: 4}
_TYPE_COUNT = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT2": 4, "MAT3": 9, "MAT4": 16}
_JSON, _BIN = 0x4E4F534A, 0x004E4942


def max_vertices(limits: InputLimits) -> int:
    """The most vertices any mesh may declare: three per allowed face (a triangle soup)."""
    return 3 * limits.max_faces


def _lines(data: bytes, keyword: bytes) -> int:
    """Lines starting with ``keyword`` and a blank (``v `` is not ``vn ``), counted without a regex or a list."""
    count = int(data.startswith(keyword + b" ") or data.startswith(keyword + b"\t"))
    for blank in (b" ", b"\t"):
        count += data.count(b"\n" + keyword + blank)
    return count


def _refuse(message: str, field_name: str, accepted: str) -> None:
    raise DsaregInputError(message, field=field_name, accepted=accepted)


def check_counts(vertices: int, faces: int | None, limits: InputLimits, field_name: str) -> None:
    """Refuse more faces than ``limits.max_faces``, more than :func:`max_vertices` vertices, or more vertices than
    ``faces`` can use (:data:`VERTICES_PER_FACE` each, plus :data:`VERTEX_SLACK`)."""
    if faces is not None and faces > limits.max_faces:
        _refuse(f"declares {faces} faces, above the limit of {limits.max_faces}", field_name,
                f"at most {limits.max_faces} faces (decimate it first)")
    ceiling = max_vertices(limits)
    if vertices > ceiling:
        _refuse(f"declares {vertices} vertices, above the limit of {ceiling}", field_name,
                f"at most {ceiling} vertices and {limits.max_faces} faces (decimate it first)")
    if faces is not None and vertices > VERTICES_PER_FACE * faces + VERTEX_SLACK:
        bound = VERTICES_PER_FACE * faces + VERTEX_SLACK
        _refuse(f"declares {vertices} vertices for {faces} faces: at most {bound} can be used "
                f"({VERTICES_PER_FACE} per face + {VERTEX_SLACK})", field_name,
                f"at most {bound} vertices for {faces} faces (remove the unused vertices first)")


def _ply_counts(data: bytes) -> tuple[int, int | None]:
    header = data[:65536].split(b"end_header", 1)[0]
    vertex = re.search(rb"element\s+vertex\s+(\d+)", header)
    face = re.search(rb"element\s+face\s+(\d+)", header)
    return (int(vertex.group(1)) if vertex else 0), (int(face.group(1)) if face else None)


def _off_counts(data: bytes) -> tuple[int, int | None]:
    text = re.sub(rb"#[^\n]*", b"", data[:65536]).lstrip()
    numbers = re.sub(rb"^[A-Z]*OFF", b"", text).split()[:2]
    try:
        return int(numbers[0]), int(numbers[1])
    except (IndexError, ValueError):
        return 0, None


def check_mesh_bytes(data: bytes, fmt: str, limits: InputLimits, field_name: str = "mesh") -> None:
    """Refuse a mesh file whose declared size exceeds the limits (see the module's docstring), before parsing.

    Raises:
        DsaregInputError: naming ``field_name``, the count found and the limit.
    """
    if fmt == "obj":
        check_counts(_lines(data, b"v"), _lines(data, b"f"), limits, field_name)
    elif fmt == "ply":
        check_counts(*_ply_counts(data), limits, field_name)
    elif fmt == "off":
        check_counts(*_off_counts(data), limits, field_name)
    elif fmt == "glb":
        check_glb(data, limits, field_name)


def _int(value, what: str, field_name: str, *, default: int | None = None) -> int:
    if value is None and default is not None:
        return default
    if not isinstance(value, int) or isinstance(value, bool) or value < 0:
        _refuse(f"GLB {what} is {str(value)[:40]!r}, not a count of bytes or items", field_name,
                "a GLB whose counts and offsets are non-negative integers")
    return value


def _glb_chunks(data: bytes, field_name: str) -> tuple[dict, int]:
    """The GLB's JSON (parsed) and its BIN chunk's length, each chunk checked to lie inside the file."""
    accepted = "a binary glTF 2.0 file (12-byte header, JSON chunk, optional BIN chunk) as long as its header says"
    if len(data) < 20:
        _refuse(f"is a GLB of {len(data)} bytes, shorter than its 20-byte header", field_name, accepted)
    _, version, total = struct.unpack_from("<III", data, 0)
    json_length, json_type = struct.unpack_from("<II", data, 12)
    if version != 2 or json_type != _JSON:
        _refuse(f"GLB version {version} or first chunk type {json_type:#x} is not glTF 2.0's", field_name, accepted)
    if total > len(data) or 20 + json_length > len(data):
        _refuse(f"GLB declares {max(total, 20 + json_length)} bytes but the file has {len(data)}", field_name, accepted)
    if json_length > GLB_MAX_JSON_BYTES:
        _refuse(f"GLB JSON chunk is {json_length} bytes, above the limit of {GLB_MAX_JSON_BYTES}", field_name, accepted)
    try:
        gltf = json.loads(data[20:20 + json_length])
    except (ValueError, RecursionError):
        gltf = None
    if not isinstance(gltf, dict):
        _refuse("GLB JSON chunk is not a JSON object", field_name, accepted)
    start = 20 + json_length + (-json_length % 4)
    bin_length = 0
    if start + 8 <= len(data):
        bin_length, bin_type = struct.unpack_from("<II", data, start)
        if bin_type != _BIN or start + 8 + bin_length > len(data):
            _refuse(f"GLB BIN chunk declares {bin_length} bytes at {start + 8}; the file has {len(data)}",
                    field_name, accepted)
    return gltf, bin_length


def _list(gltf: dict, key: str, field_name: str) -> list:
    items = gltf.get(key, [])
    if not isinstance(items, list) or not all(isinstance(item, dict) for item in items):
        _refuse(f"GLB '{key}' is not a list of objects", field_name, "a glTF 2.0 document")
    return items


def _view_lengths(gltf: dict, bin_length: int, size: int, field_name: str) -> list[int]:
    """Each buffer view's length, checked to lie inside its buffer (the BIN chunk, or at most the file)."""
    buffers = []
    for index, buffer in enumerate(_list(gltf, "buffers", field_name)):
        length = _int(buffer.get("byteLength"), f"buffers[{index}].byteLength", field_name)
        holds = size if "uri" in buffer else bin_length
        if length > holds:
            _refuse(f"GLB buffers[{index}] declares {length} bytes, above the {holds} the file holds for it",
                    field_name, "buffers no longer than the data they are given")
        buffers.append(length)
    views = []
    for index, view in enumerate(_list(gltf, "bufferViews", field_name)):
        buffer = _int(view.get("buffer"), f"bufferViews[{index}].buffer", field_name)
        offset = _int(view.get("byteOffset"), f"bufferViews[{index}].byteOffset", field_name, default=0)
        length = _int(view.get("byteLength"), f"bufferViews[{index}].byteLength", field_name)
        if buffer >= len(buffers) or offset + length > buffers[buffer]:
            holds = buffers[buffer] if buffer < len(buffers) else 0
            _refuse(f"GLB bufferViews[{index}] spans bytes {offset}..{offset + length} of buffer {buffer}, "
                    f"which holds {holds}", field_name, "buffer views inside their buffer")
        views.append(length)
    return views


def _accessor_counts(gltf: dict, views: list[int], field_name: str) -> list[int]:
    """Each accessor's count, its elements checked to lie inside its buffer view."""
    counts = []
    stride = [v.get("byteStride") for v in _list(gltf, "bufferViews", field_name)]
    for index, accessor in enumerate(_list(gltf, "accessors", field_name)):
        count = _int(accessor.get("count"), f"accessors[{index}].count", field_name)
        element = _COMPONENT_BYTES.get(accessor.get("componentType"), 4) * _TYPE_COUNT.get(accessor.get("type"), 16)
        view = accessor.get("bufferView")
        if view is not None:
            view = _int(view, f"accessors[{index}].bufferView", field_name)
            offset = _int(accessor.get("byteOffset"), f"accessors[{index}].byteOffset", field_name, default=0)
            step = stride[view] if view < len(stride) and isinstance(stride[view], int) and stride[view] else element
            need = offset + (count - 1) * step + element if count else 0
            if view >= len(views) or need > views[view]:
                _refuse(f"GLB accessors[{index}] needs {need} bytes of bufferViews[{view}], which has "
                        f"{views[view] if view < len(views) else 0}", field_name, "accessors inside their buffer view")
        counts.append(count)
    return counts


def check_glb(data: bytes, limits: InputLimits, field_name: str = "mesh") -> None:
    """A GLB's structure and size from its header and JSON chunk, before trimesh reads it."""
    gltf, bin_length = _glb_chunks(data, field_name)
    counts = _accessor_counts(gltf, _view_lengths(gltf, bin_length, len(data), field_name), field_name)
    meshes = _list(gltf, "meshes", field_name)
    per_mesh = []
    for mesh in meshes:
        vertices = faces = 0
        for primitive in mesh.get("primitives", []) if isinstance(mesh.get("primitives"), list) else []:
            attributes = primitive.get("attributes", {}) if isinstance(primitive, dict) else {}
            position, indices = attributes.get("POSITION"), primitive.get("indices")
            n = counts[position] if isinstance(position, int) and 0 <= position < len(counts) else 0
            vertices += n
            faces += (counts[indices] if isinstance(indices, int) and 0 <= indices < len(counts) else n) // 3
        per_mesh.append((vertices, faces))
    shown = [node["mesh"] for node in _list(gltf, "nodes", field_name)
             if isinstance(node.get("mesh"), int) and 0 <= node["mesh"] < len(per_mesh)] or range(len(per_mesh))
    check_counts(sum(per_mesh[m][0] for m in shown), sum(per_mesh[m][1] for m in shown), limits, field_name)


def review_bytes(data: bytes | None) -> bytes | None:
    """``data`` when the review model made of it as given stays under :data:`REVIEW_MODEL_MAX_BYTES`, else None
    (the review files then show the working mesh, which the working-face budget bounds)."""
    if data is None:
        return None
    factor = 2 if b"\x00" in bytes(data[:4096]) else 1
    return data if factor * len(data) <= REVIEW_MODEL_MAX_BYTES else None
