import gzip
import io

import nibabel as nib
import nrrd
import numpy as np
import pytest

from dsareg_engine.errors import DsaregInputError
from dsareg_engine.io.limits import InputLimits
from dsareg_engine.io.rad import format_rad_header
from dsareg_engine.io.volume_io import RAS_TO_LPS, read_volume, volume_to_mesh


def _nifti_bytes(volume, affine_lps, gz=False) -> bytes:
    data = nib.Nifti1Image(volume, RAS_TO_LPS @ affine_lps).to_bytes()
    return gzip.compress(data) if gz else data


def _nrrd_bytes(volume, affine_lps, space="left-posterior-superior") -> bytes:
    import os
    import tempfile

    header = {
        "space": space,
        "space directions": affine_lps[:3, :3].T,
        "space origin": affine_lps[:3, 3],
        "encoding": "raw",
    }
    if space == "right-anterior-superior":
        ras = RAS_TO_LPS @ affine_lps
        header.update({"space directions": ras[:3, :3].T, "space origin": ras[:3, 3]})
    with tempfile.TemporaryDirectory() as folder:
        path = os.path.join(folder, "v.nrrd")
        nrrd.write(path, volume, header, index_order="F")
        with open(path, "rb") as handle:
            return handle.read()


def _assert_on_surface(mesh, tree, pitch):
    distance = tree.query(mesh.vertices)[0]
    assert np.percentile(distance, 99.5) < pitch, np.percentile(distance, [50, 99, 99.5, 100])
    # The few worst vertices sit in the creases where overlapping phantom tubes meet, which
    # marching cubes (and its light smoothing) rounds off by up to ~2 voxels.
    assert distance.max() < 2.0 * pitch
    assert np.median(distance) < 0.25 * pitch


@pytest.mark.parametrize("gz", [False, True])
def test_nifti_round_trip_lands_on_the_phantom(phantom_volume, phantom_surface_tree, small_phantom, gz):
    volume, affine, pitch = phantom_volume
    loaded = read_volume(_nifti_bytes(volume, affine, gz), "phantom.nii.gz" if gz else "phantom.nii")
    assert loaded.kind == "nifti"
    np.testing.assert_allclose(loaded.affine, affine, atol=1e-5)  # RAS file → LPS world
    mesh = volume_to_mesh(loaded)
    _assert_on_surface(mesh, phantom_surface_tree, pitch)
    np.testing.assert_allclose(mesh.vertices.min(0), small_phantom.vertices.min(0), atol=pitch)
    np.testing.assert_allclose(mesh.vertices.max(0), small_phantom.vertices.max(0), atol=pitch)


def test_dicom_series_round_trip(phantom_volume, phantom_surface_tree, build):
    volume, affine, pitch = phantom_volume
    parts = build.ct_series(volume, affine)
    rng = np.random.default_rng(0)
    shuffled = [parts[i] for i in rng.permutation(len(parts))]  # the reader sorts by position
    loaded = read_volume(shuffled)
    assert loaded.kind == "dicom-series"
    np.testing.assert_allclose(loaded.affine, affine, atol=1e-4)
    np.testing.assert_allclose(loaded.data, volume, atol=0.51)
    _assert_on_surface(volume_to_mesh(loaded), phantom_surface_tree, pitch)


@pytest.mark.parametrize("space", ["left-posterior-superior", "right-anterior-superior"])
def test_nrrd(phantom_volume, space):
    volume, affine, _ = phantom_volume
    loaded = read_volume(_nrrd_bytes(volume, affine, space), "v.nrrd")
    assert loaded.kind == "nrrd"
    np.testing.assert_allclose(loaded.affine, affine, atol=1e-6)
    np.testing.assert_allclose(loaded.data, volume)


def test_rad_raw_volume_pair():
    volume = np.zeros((6, 7, 8), np.float32)
    volume[2:4, 3:5, 1:7] = 100.0
    header = format_rad_header(volume.shape, (0.5, 0.5, 0.5), "float", np.eye(4))
    raw = volume.transpose(2, 1, 0).astype("<f4").tobytes()
    loaded = read_volume([raw, header])
    assert loaded.kind == "rad"
    np.testing.assert_array_equal(loaded.data, volume)
    mesh = volume_to_mesh(loaded)
    assert mesh.vertices[:, 2].min() > 0.0 and mesh.vertices[:, 2].max() < 3.5


def test_mesh_normals_point_outward(phantom_volume):
    volume, affine, _ = phantom_volume
    mesh = volume_to_mesh(volume, RAS_TO_LPS @ affine)  # a mirrored affine too
    triangles = mesh.vertices[mesh.faces]
    signed = np.einsum("ij,ij->i", triangles[:, 0], np.cross(triangles[:, 1], triangles[:, 2])).sum()
    assert signed > 0


def test_nothing_above_threshold():
    with pytest.raises(DsaregInputError, match="constant|nothing"):
        volume_to_mesh(np.zeros((10, 10, 10), np.float32), np.eye(4))
    empty = read_volume(_nifti_bytes(np.zeros((8, 8, 8), np.float32), np.eye(4)), "empty.nii")
    with pytest.raises(DsaregInputError, match="constant") as info:
        volume_to_mesh(empty)
    assert info.value.field == "volume"
    speck = np.zeros((10, 10, 10), np.float32)
    speck[5, 5, 5] = 1.0
    with pytest.raises(DsaregInputError):
        volume_to_mesh(speck, np.eye(4))


def test_size_limit_checked_from_header():
    header = nib.Nifti1Header()
    header.set_data_shape((2048, 2048, 2048))
    header.set_data_dtype(np.int16)
    buffer = io.BytesIO()
    header.write_to(buffer)
    data = buffer.getvalue() + b"\x00" * 4  # 16 GiB declared, 352 bytes sent
    with pytest.raises(DsaregInputError, match="above the limit"):
        read_volume(data, "huge.nii")
    small = _nifti_bytes(np.ones((20, 20, 20), np.float32), np.eye(4))
    with pytest.raises(DsaregInputError, match="above the limit"):
        read_volume(small, "v.nii", InputLimits(max_volume_bytes=1000))


def test_bad_volume_inputs(phantom_volume):
    volume, affine, _ = phantom_volume
    nifti = _nifti_bytes(volume, affine)
    with pytest.raises(DsaregInputError, match="empty"):
        read_volume(b"", "v.nii")
    with pytest.raises(DsaregInputError, match="truncated|unreadable"):
        read_volume(nifti[: len(nifti) // 2], "v.nii")
    with pytest.raises(DsaregInputError, match="truncated|corrupt"):
        read_volume(gzip.compress(nifti)[:2000], "v.nii.gz")
    with pytest.raises(DsaregInputError, match="not a recognised"):
        read_volume(b"just some text " * 40, "v.nii")
    with pytest.raises(DsaregInputError, match=r"\.raw"):
        read_volume(format_rad_header((4, 4, 4), (1, 1, 1)), "v.rad")
    with pytest.raises(DsaregInputError, match="4D|3D volume"):
        read_volume(nib.Nifti1Image(np.zeros((4, 4, 4, 3), np.float32), np.eye(4)).to_bytes())


def test_bad_dicom_series(phantom_volume, build):
    volume, affine, _ = phantom_volume
    parts = build.ct_series(volume[:, :, :6], affine)
    with pytest.raises(DsaregInputError, match="not evenly spaced"):
        read_volume(parts[:2] + parts[3:])
    with pytest.raises(DsaregInputError, match="duplicate"):
        read_volume(parts + parts[:1])
    with pytest.raises(DsaregInputError, match="single-slice"):
        read_volume(parts[0], "slice.dcm")
    with pytest.raises(DsaregInputError, match="empty"):
        read_volume(parts[:3] + [b""])


def _enhanced_bytes(volume, affine) -> bytes:
    from pydicom.dataset import Dataset, FileMetaDataset
    from pydicom.sequence import Sequence
    from pydicom.uid import ExplicitVRLittleEndian, generate_uid

    meta = FileMetaDataset()
    meta.MediaStorageSOPClassUID = "1.2.840.10008.5.1.4.1.1.2.1"  # enhanced CT
    meta.MediaStorageSOPInstanceUID = generate_uid()
    meta.TransferSyntaxUID = ExplicitVRLittleEndian
    ds = Dataset()
    ds.file_meta = meta
    ds.SOPClassUID, ds.SOPInstanceUID = meta.MediaStorageSOPClassUID, meta.MediaStorageSOPInstanceUID
    ds.Rows, ds.Columns, ds.NumberOfFrames = volume.shape[1], volume.shape[0], volume.shape[2]
    ds.BitsAllocated, ds.BitsStored, ds.HighBit, ds.PixelRepresentation = 16, 16, 15, 0
    ds.SamplesPerPixel, ds.PhotometricInterpretation = 1, "MONOCHROME2"
    spacing = np.linalg.norm(affine[:3, :3], axis=0)
    shared = Dataset()
    orientation, measures = Dataset(), Dataset()
    orientation.ImageOrientationPatient = [*(affine[:3, 0] / spacing[0]), *(affine[:3, 1] / spacing[1])]
    measures.PixelSpacing = [float(spacing[1]), float(spacing[0])]
    shared.PlaneOrientationSequence = Sequence([orientation])
    shared.PixelMeasuresSequence = Sequence([measures])
    ds.SharedFunctionalGroupsSequence = Sequence([shared])
    frames = []
    for k in range(volume.shape[2]):
        item, position = Dataset(), Dataset()
        position.ImagePositionPatient = [float(x) for x in affine[:3, :3] @ [0, 0, k] + affine[:3, 3]]
        item.PlanePositionSequence = Sequence([position])
        frames.append(item)
    ds.PerFrameFunctionalGroupsSequence = Sequence(frames[::-1])  # stored head-first: the reader sorts
    ds.PixelData = np.round(volume[:, :, ::-1].transpose(2, 1, 0)).astype(np.uint16).tobytes()
    buffer = io.BytesIO()
    ds.save_as(buffer, enforce_file_format=True)
    return buffer.getvalue()


def test_enhanced_multiframe_dicom(phantom_volume):
    volume, affine, _ = phantom_volume
    loaded = read_volume(_enhanced_bytes(volume, affine), "enhanced.dcm")
    assert loaded.kind == "dicom-enhanced"
    np.testing.assert_allclose(loaded.affine, affine, atol=1e-4)
    np.testing.assert_allclose(loaded.data, np.round(volume), atol=1e-3)
    with pytest.raises(DsaregInputError, match="above the limit"):
        read_volume(_enhanced_bytes(volume, affine), "enhanced.dcm", InputLimits(max_volume_bytes=10_000))


def test_an_enhanced_volume_among_other_series_is_read_with_a_warning(phantom_volume, build):
    """A folder holding an enhanced multi-frame CT and the XA runs: the CT is the volume (its frames are its
    slices), also given as ``FileParts``, and the warning names what was left out."""
    import pydicom

    from dsareg_engine.io.file_parts import FileParts

    volume, affine, _ = phantom_volume
    enhanced = pydicom.dcmread(io.BytesIO(_enhanced_bytes(volume, affine)))
    enhanced.Modality = "CT"
    out = io.BytesIO()
    enhanced.save_as(out, enforce_file_format=True)
    files = [build.xa(primary=0.0), out.getvalue(), build.xa(primary=90.0)]
    for given in (files, FileParts(lambda f=f: f for f in files)):
        loaded = read_volume(given, "folder")
        assert loaded.kind == "dicom-enhanced" and loaded.data.shape == volume.shape
        np.testing.assert_allclose(loaded.data, np.round(volume), atol=1e-3)
        assert any("left out" in warning and "XA" in warning for warning in loaded.warnings), loaded.warnings


def test_limits_are_validated():
    with pytest.raises(ValueError):
        InputLimits(max_faces=0)
    assert InputLimits().working_faces == 20_000 and InputLimits().max_faces == 500_000
