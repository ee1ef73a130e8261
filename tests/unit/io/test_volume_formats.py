"""MetaImage, detached NRRD and legacy VTK image volumes (SimpleITK), on volumes the tests write."""

import locale

import numpy as np
import pytest

from dsareg_engine.errors import DsaregInputError
from dsareg_engine.io.limits import InputLimits
from dsareg_engine.io.volume_formats import detached_data_file, detect_itk_format
from dsareg_engine.io.volume_io import detect_volume_format, read_volume

DIRECTION = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
SPACING = (0.4, 0.5, 0.6)
ORIGIN = (-10.0, 20.0, 5.0)
VOXELS = np.arange(4 * 5 * 6, dtype=np.int16).reshape(4, 5, 6)  # [i, j, k], every voxel its own value


def _image():
    import SimpleITK as sitk

    image = sitk.GetImageFromArray(VOXELS.transpose(2, 1, 0))  # SimpleITK's array is [k, j, i]
    image.SetDirection(DIRECTION.ravel().tolist())
    image.SetSpacing(SPACING)
    image.SetOrigin(ORIGIN)
    return image


def _written(tmp_path, name: str, compress: bool = False) -> list[bytes]:
    import SimpleITK as sitk

    sitk.WriteImage(_image(), str(tmp_path / name), compress)
    parts = sorted(tmp_path.iterdir(), key=lambda p: p.suffix not in (".mha", ".mhd", ".nhdr"))
    return [p.read_bytes() for p in parts]


def _expect_geometry(volume):
    image = _image()
    assert np.array_equal(volume.data, VOXELS.astype(np.float32))
    for index in ((0, 0, 0), (3, 1, 2), (1, 4, 5)):
        world = volume.affine @ np.array([*index, 1.0])
        assert np.allclose(world[:3], image.TransformIndexToPhysicalPoint(index), atol=1e-6)  # ITK's LPS mm


@pytest.mark.parametrize("name, compress", [("v.mha", False), ("v.mha", True), ("v.mhd", False), ("v.nhdr", True)])
def test_itk_formats_keep_voxels_and_geometry(tmp_path, name, compress):
    parts = _written(tmp_path, name, compress)
    assert len(parts) == (1 if name.endswith(".mha") else 2)
    volume = read_volume(parts if len(parts) > 1 else parts[0], name)
    _expect_geometry(volume)
    if len(parts) == 2:  # the data file first: the header is found by its content
        _expect_geometry(read_volume(parts[::-1], name))


def test_detached_nrrd_reads_as_the_attached_one(tmp_path):
    import nrrd

    header = {"space": "right-anterior-superior", "space directions": np.diag(SPACING),
              "space origin": np.array(ORIGIN), "encoding": "raw", "endian": "little"}
    nrrd.write(str(tmp_path / "a.nrrd"), VOXELS, header, index_order="F")
    attached = (tmp_path / "a.nrrd").read_bytes()
    text, data = attached.split(b"\n\n", 1)
    detached = text + b"\ndata file: ../elsewhere/a.raw\n\n"  # the named path is never followed
    assert detached_data_file(detached, "nrrd") == "../elsewhere/a.raw"
    one, two = read_volume(attached), read_volume([detached, data])
    assert np.array_equal(one.data, two.data) and np.allclose(one.affine, two.affine)


def test_legacy_vtk_structured_points():
    values = " ".join(str(v) for v in VOXELS.transpose(2, 1, 0).ravel())  # x fastest
    data = (f"# vtk DataFile Version 3.0\npc-mra speed\nASCII\nDATASET STRUCTURED_POINTS\nDIMENSIONS 4 5 6\n"
            f"SPACING 0.4 0.5 0.6\nORIGIN -10 20 5\nPOINT_DATA 120\nSCALARS speed short\nLOOKUP_TABLE default\n"
            f"{values}\n").encode()
    assert detect_volume_format(data) == "vtk-image" and detect_itk_format(data) == "vtk-image"
    before = locale.setlocale(locale.LC_ALL, None)
    volume = read_volume(data, "carotid.vtk")
    assert np.array_equal(volume.data, VOXELS.astype(np.float32))
    assert np.allclose(volume.affine[:3, :3], np.diag(SPACING)) and np.allclose(volume.affine[:3, 3], ORIGIN)
    assert "no patient space" in volume.warnings[0]
    assert locale.setlocale(locale.LC_ALL, None) == before  # ITK's VTK reader left "C" behind: open() read ASCII


def test_detached_headers_need_their_one_data_file(tmp_path):
    header, data = _written(tmp_path, "v.mhd")
    with pytest.raises(DsaregInputError, match="needs its data file 'v.raw'"):
        read_volume(header, "v.mhd")
    spaced = header.replace(b"ElementDataFile = v.raw", b"ElementDataFile = scan 1 of 2.raw")
    assert np.array_equal(read_volume([spaced, data]).data, VOXELS.astype(np.float32))  # any one name is rewritten
    listed = header.replace(b"ElementDataFile = v.raw", b"ElementDataFile = LIST")
    with pytest.raises(DsaregInputError, match="several files"):
        read_volume([listed, data])
    with pytest.raises(DsaregInputError, match="truncated"):
        read_volume([header, data[: len(data) // 2]])


def test_declared_size_checked_before_reading(tmp_path):
    header, data = _written(tmp_path, "v.mhd")
    with pytest.raises(DsaregInputError, match="above the limit"):
        read_volume([header, data], limits=InputLimits(max_volume_bytes=100))


@pytest.mark.parametrize("line", [b"data file: LIST\nslice1.raw\nslice2.raw", b"data file: s%03d.raw 1 4 1"])
def test_a_nrrd_split_over_several_files_is_refused_naming_it(tmp_path, line):
    """Issue 43 item 7: a NRRD header with a list of data files read as 'not enough values to unpack'."""
    header = (b"NRRD0004\ntype: short\ndimension: 3\nsizes: 4 5 6\nencoding: raw\n"
              b"space: left-posterior-superior\nspace directions: (1,0,0) (0,1,0) (0,0,1)\n" + line + b"\n\n")
    for parts in ([header, VOXELS.tobytes()], header):  # with a data file, and the header alone
        with pytest.raises(DsaregInputError, match="split over several files") as refused:
            read_volume(parts, "v.nhdr") if isinstance(parts, bytes) else read_volume(parts)
        assert "a header with one data file" in str(refused.value)
