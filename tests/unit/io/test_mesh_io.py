import struct

import numpy as np
import pytest
import trimesh
from scipy.spatial import cKDTree

from dsareg_engine.errors import DsaregInputError
from dsareg_engine.io.limits import InputLimits
from dsareg_engine.io.mesh_io import _cluster_decimate, decimate, detect_mesh_format, read_mesh, read_mesh_detailed
from dsareg_engine.simulation.phantom import make_vessel_phantom

TRIANGLE_OBJ = b"v 0 0 0\nv 10 0 0\nv 0 10 0\nf 1 2 3\n"


@pytest.fixture(scope="module")
def phantom():
    return make_vessel_phantom(depth=2)


def _export(mesh, file_type: str) -> bytes:
    data = trimesh.Trimesh(mesh.vertices, mesh.faces, process=False).export(file_type=file_type)
    return data.encode() if isinstance(data, str) else data


@pytest.mark.parametrize(
    "file_type, fmt",
    [("obj", "obj"), ("stl", "stl"), ("stl_ascii", "stl"), ("ply", "ply"), ("off", "off"), ("glb", "glb")],
)
def test_formats_round_trip(phantom, file_type, fmt):
    data = _export(phantom, file_type)
    if fmt == "glb":  # glTF's unit is the metre (tests/unit/io/test_mesh_units.py)
        data = _export(phantom.transformed(np.diag([1e-3, 1e-3, 1e-3, 1.0])), file_type)
    assert detect_mesh_format(data) == fmt
    result = read_mesh_detailed(data, f"vessels.{fmt}")
    assert result.format == fmt and not result.warnings
    assert result.mesh.n_faces == phantom.n_faces
    distance = cKDTree(result.mesh.vertices).query(phantom.vertices)[0]
    assert distance.max() < 1e-4  # same surface, mm preserved


def test_wrong_or_missing_extension_detected_from_content(phantom):
    result = read_mesh_detailed(_export(phantom, "stl"), "vessels.obj")
    assert result.format == "stl" and "content is STL" in result.warnings[0]
    assert read_mesh(_export(phantom, "ply"), None).n_faces == phantom.n_faces


def test_mtllib_never_followed():
    data = b"mtllib /etc/passwd\nusemtl evil\n" + TRIANGLE_OBJ
    assert read_mesh(data, "a.obj").n_faces == 1


@pytest.mark.parametrize(
    "data, name, match",
    [
        (b"", "a.stl", "empty"),
        (b"hello world, not a mesh", None, "not a recognised"),
        (b"v 0 0 0\nv 1 0 0\nv 0 1 0\n", "a.obj", "no faces|could not be parsed"),
        (b"v 0 0 nan\nv 1 0 0\nv 0 1 0\nf 1 2 3\n", "a.obj", "NaN or infinite"),
        (b"v 0 0 inf\nv 1 0 0\nv 0 1 0\nf 1 2 3\n", "a.obj", "NaN or infinite"),
        (b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 9\n", "a.obj", "out of bounds|indices"),
        (b"OFF\n3 1 0\n0 0 0\n1 0 0\n0 1 0\n3 0 1 7\n", "a.off", "indices span|out of bounds|could not"),
        (b"v 0 0 0\nv 0 0 0\nv 0 0 0\nf 1 2 3\n", "a.obj", "degenerate"),
    ],
)
def test_bad_meshes(data, name, match):
    with pytest.raises(DsaregInputError, match=match) as info:
        read_mesh(data, name)
    assert info.value.field == "mesh"


def test_truncated_binary_stl(phantom):
    data = _export(phantom, "stl")
    with pytest.raises(DsaregInputError, match="truncated|could not"):
        read_mesh(data[: len(data) // 2], "a.stl")
    with pytest.raises(DsaregInputError):
        read_mesh(data[:60], "a.stl")


def test_truncated_ply(phantom):
    data = _export(phantom, "ply")
    with pytest.raises(DsaregInputError):
        read_mesh(data[: len(data) // 3], "a.ply")


def test_face_ceiling_checked_from_header():
    header = b"\x00" * 80 + struct.pack("<I", 2_000_000)  # declares 2M faces, holds none
    data = header + b"\x00" * 50  # not a consistent binary STL
    with pytest.raises(DsaregInputError):
        read_mesh(data, "big.stl")
    ply = (
        b"ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\n"
        b"element face 900000\nproperty list uchar int vertex_indices\nend_header\n"
    )
    with pytest.raises(DsaregInputError, match="declares 900000 faces"):
        read_mesh(ply, "big.ply")
    with pytest.raises(DsaregInputError, match="limit of 10"):
        read_mesh(_export(make_vessel_phantom(depth=0), "ply"), "a.ply", InputLimits(max_faces=10, working_faces=5))


def _surface_distance(original, reduced) -> np.ndarray:
    """Distance from every original vertex to a dense sampling of the reduced surface (mm)."""
    samples, _ = trimesh.sample.sample_surface(
        trimesh.Trimesh(reduced.vertices, reduced.faces, process=False), 150_000, seed=0
    )
    return cKDTree(samples).query(original.vertices)[0]


def test_decimation_keeps_thin_tubes():
    fine = make_vessel_phantom(n_sides=16, rings_per_segment=40)  # ~40k faces, thinnest radius ~0.45 mm
    result = read_mesh_detailed(_export(fine, "ply"), "fine.ply", InputLimits(working_faces=4000))
    assert result.original_faces == fine.n_faces and result.mesh.n_faces <= 4000
    assert "decimated" in result.warnings[0]
    distance = _surface_distance(fine, result.mesh)
    assert distance.max() < 0.3, distance.max()  # no branch collapsed: every original point is still on the surface
    # the fallback, vertex clustering, is markedly worse at the same budget (what quadric decimation buys)
    clustered = _cluster_decimate(fine, 4000)
    assert clustered.n_faces <= 4000
    assert _surface_distance(fine, clustered).max() > distance.max()


def test_decimate_noop_under_budget(phantom):
    assert decimate(phantom, phantom.n_faces + 1) is phantom


def test_binary_stl_whose_header_says_solid(phantom):
    data = bytearray(_export(phantom, "stl"))
    data[:12] = b"solid vessel"
    result = read_mesh_detailed(bytes(data), "a.stl")
    assert result.format == "stl" and result.mesh.n_faces == phantom.n_faces


@pytest.mark.parametrize("face", [b"f 0 1 2", b"f 1 2 0", b"f 0/1 2/2 3/3", b"  f 2 0 3\r"])
def test_obj_vertex_index_zero_is_refused(face):
    """OBJ indices are 1-based: trimesh would read 0 as -1, i.e. silently the last vertex."""
    data = b"v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nf 1 2 3\n" + face + b"\n"
    with pytest.raises(DsaregInputError, match="index 0") as caught:
        read_mesh(data, "m.obj")
    assert caught.value.field == "mesh"
    mesh = read_mesh(b"v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nf 1 2 3\nf 1/1 2/10 4/0\n", "m.obj")  # 0 in texture refs
    assert mesh.n_faces == 2
