"""Mesh inputs bounded by their downstream cost (issue 43 items 6 and 7): vertices as well as faces, a GLB's
structure, the review model's size; every refusal names the field, the count and the limit, before parsing."""

from __future__ import annotations

import json
import struct
import time

import numpy as np
import pytest

from dsareg_engine.errors import DsaregInputError
from dsareg_engine.io.limits import InputLimits
from dsareg_engine.io.mesh_io import read_mesh_detailed
from dsareg_engine.io.mesh_limits import REVIEW_MODEL_MAX_BYTES, max_vertices, review_bytes

TETRA = b"v 0 0 0\nv 10 0 0\nv 0 10 0\nv 0 0 10\nf 1 2 3\nf 1 2 4\nf 1 3 4\nf 2 3 4\n"


def _refusal(data: bytes, name: str, limits: InputLimits | None = None) -> str:
    with pytest.raises(DsaregInputError) as caught:
        read_mesh_detailed(data, name, limits or InputLimits(), field_name="mesh")
    assert caught.value.field == "mesh" and caught.value.accepted
    return caught.value.message


def _strip(n: int) -> bytes:
    """An OBJ triangle strip of ``n`` faces (every vertex used)."""
    rows = [f"v {i} {i % 2} 0" for i in range(n + 2)] + [f"f {i + 1} {i + 2} {i + 3}" for i in range(n)]
    return ("\n".join(rows) + "\n").encode()


def test_unused_vertices_are_refused_before_the_review_model_is_made():
    data = _strip(12_000) + b"v 1 2 3\n" * 1_000_000  # 12k faces, 1 M vertices no face uses (the 26 MB)
    started = time.perf_counter()
    message = _refusal(data, "vessels.obj")
    assert time.perf_counter() - started < 2.0
    assert "1012002 vertices for 12000 faces" in message and "at most 49024" in message
    assert read_mesh_detailed(_strip(300), "strip.obj").mesh.n_faces == 300  # a mesh that uses them is read


def test_millions_of_vertex_lines_are_counted_not_parsed():
    data = b"f 1 2 3\n" + b"v 0 0 0\n" * 2_000_000  # 10 M lines were a MemoryError after 15 s; now refused in 1.7 s
    started = time.perf_counter()
    message = _refusal(data, "huge.obj")
    assert time.perf_counter() - started < 2.0
    assert f"declares 2000000 vertices, above the limit of {max_vertices(InputLimits())}" in message


def test_ply_and_off_headers_are_checked_before_the_body():
    ply = b"ply\nformat ascii 1.0\nelement vertex 900000\nproperty float x\nproperty float y\nproperty float z\n" \
          b"element face 10\nproperty list uchar int vertex_indices\nend_header\n"
    assert "900000 vertices for 10 faces" in _refusal(ply, "m.ply")
    assert "declares 2000 vertices, above the limit of 30" in _refusal(b"OFF\n2000 1 0\n", "m.off", InputLimits(10, 10))


def _glb(gltf: dict, binary: bytes) -> bytes:
    text = json.dumps(gltf).encode()
    text += b" " * (-len(text) % 4)
    binary += b"\0" * (-len(binary) % 4)
    body = struct.pack("<II", len(text), 0x4E4F534A) + text + struct.pack("<II", len(binary), 0x004E4942) + binary
    return struct.pack("<III", 0x46546C67, 2, 12 + len(body)) + body


def _triangle_glb(view_length: int = 36, nodes: int = 1, count: int = 3) -> bytes:
    positions = np.array([[0, 0, 0], [10, 0, 0], [0, 10, 0]], np.float32).tobytes()
    indices = np.array([0, 1, 2, 0], np.uint16).tobytes()
    return _glb({"asset": {"version": "2.0"}, "buffers": [{"byteLength": 44}],
                 "bufferViews": [{"buffer": 0, "byteLength": view_length}, {"buffer": 0, "byteOffset": 36,
                                                                             "byteLength": 6}],
                 "accessors": [{"bufferView": 0, "componentType": 5126, "count": count, "type": "VEC3",
                                "min": [0, 0, 0], "max": [10, 10, 0]},
                               {"bufferView": 1, "componentType": 5123, "count": 3, "type": "SCALAR"}],
                 "meshes": [{"primitives": [{"attributes": {"POSITION": 0}, "indices": 1}]}],
                 "nodes": [{"mesh": 0}] * nodes, "scenes": [{"nodes": list(range(nodes))}]}, positions + indices)


def test_hostile_glb_structure_is_refused_with_the_field_and_the_limit():
    assert read_mesh_detailed(_triangle_glb(), "m.glb").mesh.n_faces == 1
    assert "bufferViews[0] spans bytes 0..1099511627776 of buffer 0, which holds 44" in _refusal(
        _triangle_glb(view_length=2**40), "m.glb")  # was "AssertionError:"
    assert "accessors[0] needs 1200000000 bytes of bufferViews[0], which has 36" in _refusal(
        _triangle_glb(count=100_000_000), "m.glb")
    assert "declares 1000 faces, above the limit of 100" in _refusal(_triangle_glb(nodes=1000), "m.glb",
                                                                        InputLimits(100, 100))
    assert "GLB declares" in _refusal(_triangle_glb()[:-8], "m.glb")


def test_the_review_model_is_bounded(tmp_path):
    from dsareg_engine.io.review_files import write_model_json
    from dsareg_engine.mesh import mesh_from_arrays

    big = TETRA + b"# padding\n" * (REVIEW_MODEL_MAX_BYTES // 10 + 1)
    assert review_bytes(TETRA) == TETRA and review_bytes(big) is None
    working = mesh_from_arrays(np.array([[0, 0, 0], [9, 0, 0], [0, 9, 0]], float), np.array([[0, 1, 2]]), max_faces=9)
    poses = {"mesh_to_world": np.eye(4).tolist(), "initial_mesh_to_world": np.eye(4).tolist()}
    write_model_json(tmp_path, big, "m.obj", working, poses)
    document = json.loads((tmp_path / "model.json").read_text())
    assert document["vertex_order"] == "working mesh" and document["vertex_count"] == 3
    write_model_json(tmp_path, TETRA, "m.obj", working, poses)
    assert json.loads((tmp_path / "model.json").read_text())["vertex_count"] == 4
