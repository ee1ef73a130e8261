"""A volume's declared shape from its header alone (every format), and the expected cost of its first read."""

import gzip
import io

import numpy as np
import pytest

from dsareg_engine.errors import DsaregInputError
from dsareg_engine.io.limits import InputLimits
from dsareg_engine.io.model_cache import DirectoryModelStore, model_key
from dsareg_engine.io.volume_cost import MEASURED, MEASURED_MRA, declared_volume, expected_read_cost, volume_read_cost
from dsareg_engine.io.volume_io import read_volume

VOXELS = np.arange(7 * 5 * 6, dtype=np.int16).reshape(7, 5, 6)


@pytest.fixture(scope="module")
def series():
    """A small CT series (files): 24 x 20 x 9 voxels of 0.8 x 0.8 x 1.5 mm."""
    from dsareg_engine.simulation.synthetic_volume_dicom import cta_series

    data = np.random.default_rng(0).uniform(-100, 400, (24, 20, 9)).astype(np.float32)
    return cta_series(data, np.diag([0.8, 0.8, 1.5, 1.0]), "a")[0]


def _nifti(voxels=VOXELS) -> bytes:
    import nibabel as nib

    return nib.Nifti1Image(voxels, np.diag([0.5, 0.5, 0.7, 1.0])).to_bytes()


def _nrrd(tmp_path) -> bytes:
    import nrrd

    nrrd.write(str(tmp_path / "v.nrrd"), VOXELS, {"space": "left-posterior-superior",
                                                   "space directions": np.diag([0.5, 0.5, 0.7])}, index_order="F")
    return (tmp_path / "v.nrrd").read_bytes()


def _mha(tmp_path) -> bytes:
    import SimpleITK as sitk

    sitk.WriteImage(sitk.GetImageFromArray(VOXELS.transpose(2, 1, 0)), str(tmp_path / "v.mha"))
    return (tmp_path / "v.mha").read_bytes()


@pytest.mark.parametrize("fmt", ["nifti", "nifti.gz", "nrrd", "mha"])
def test_the_declared_shape_is_the_shape_a_read_gives(tmp_path, fmt):
    data = {"nifti": lambda _: _nifti(), "nifti.gz": lambda _: gzip.compress(_nifti()), "nrrd": _nrrd,
            "mha": _mha}[fmt](tmp_path)
    assert declared_volume(data, f"v.{fmt}") == read_volume(data, f"v.{fmt}").data.shape == VOXELS.shape


def test_a_dicom_series_declares_its_shape_without_decoding_a_slice(series):
    shape = read_volume(series).data.shape
    assert declared_volume(series) == shape
    from pydicom import dcmread
    from pydicom.uid import ExplicitVRLittleEndian

    broken = []
    for part in series:  # every slice's pixel data cut short: a read fails, the header is whole
        dataset = dcmread(io.BytesIO(part))
        dataset.file_meta.TransferSyntaxUID = ExplicitVRLittleEndian
        dataset.PixelData = dataset.PixelData[:10]
        out = io.BytesIO()
        dataset.save_as(out, enforce_file_format=True)
        broken.append(out.getvalue())
    with pytest.raises(DsaregInputError):
        read_volume(broken)
    assert declared_volume(broken) == shape


def test_the_header_is_still_checked():
    truncated = _nifti()[:348 + 4 + 20]  # the header whole, the voxels cut: declared, never decoded
    assert declared_volume(truncated, "v.nii") == VOXELS.shape
    with pytest.raises(DsaregInputError, match="above the limit"):
        declared_volume(_nifti(), "v.nii", InputLimits(max_volume_bytes=64))
    with pytest.raises(DsaregInputError, match="not a recognised volume"):
        declared_volume(b"\x00" * 2048, "v.bin")


@pytest.mark.parametrize("kind, table", [("cta", MEASURED), ("mra", MEASURED_MRA)])
def test_the_expected_cost_follows_the_measured_reads(kind, table):
    for voxels, memory_mb, cpu_s in table:
        assert expected_read_cost(int(voxels), kind) == pytest.approx((memory_mb, cpu_s))
    sizes = [0, 10**5, 10**6, 10**7, 5 * 10**7, 10**8, 2 * 10**8, 4 * 10**8]
    costs = [expected_read_cost(n, kind) for n in sizes]
    assert all(a[0] < b[0] and a[1] <= b[1] for a, b in zip(costs, costs[1:]))  # more voxels: never less
    (n0, m0, c0), (n1, m1, c1) = table[-2:]
    beyond = expected_read_cost(int(2 * n1), kind)  # past the largest measured read: at its last slope
    assert beyond[0] == pytest.approx(m1 + n1 * (m1 - m0) / (n1 - n0))


def test_a_volume_of_no_known_kind_is_expected_to_cost_the_larger_of_a_cta_and_a_tof_read():
    """A TOF slab takes more address space than a CTA of its voxels (the 160-slice slab: 1.4 GB, the CTA curve 0.9);
    a NIfTI says neither, so it gets the larger; past the TOF slabs measured, the largest of them (a whole-head
    CTA in NIfTI is not sized as a TOF extrapolated to 600 slices)."""
    tof_voxels, tof_mb, _ = MEASURED_MRA[-2]
    assert expected_read_cost(int(tof_voxels))[0] == pytest.approx(tof_mb)
    assert tof_mb > expected_read_cost(int(tof_voxels), "cta")[0]
    for voxels in (10**6, 10**7, 6 * 10**7, 2 * 10**8, 4 * 10**8):
        unknown, cta = expected_read_cost(voxels), expected_read_cost(voxels, "cta")
        capped = expected_read_cost(min(voxels, int(MEASURED_MRA[-1][0])), "mra")
        assert unknown == (max(cta[0], capped[0]), max(cta[1], capped[1]))
    assert expected_read_cost(4 * 10**8)[0] == MEASURED_MRA[-1][1]  # not the TOF's slope extrapolated


def test_a_kept_model_costs_its_headers_only(tmp_path, series):
    first = volume_read_cost(series, "volume.dcm", store=DirectoryModelStore(tmp_path))
    assert not first.cached and first.voxels == int(np.prod(first.shape))
    assert (first.memory_mb, first.cpu_s) == expected_read_cost(first.voxels, "cta")  # a CT series: a CTA's read

    class Kept:  # a store holding this volume's model (any object: only its presence counts)
        def get(self, key):
            return object() if key == model_key(series, "volume.dcm", None, 20_000) else None

    kept = volume_read_cost(series, "volume.dcm", store=Kept())
    assert kept.cached and kept.shape == first.shape and kept.memory_mb < first.memory_mb


def test_an_mr_series_or_a_given_kind_is_sized_as_its_read(series, tmp_path):
    """The series' Modality (read with its header, no voxel decoded) or ``volume_kind`` picks the curve: MR a TOF's,
    CT a CTA's; a NIfTI of no kind the larger of the two."""
    import io

    import pydicom

    from dsareg_engine.io.volume_kind import VolumeReading

    def with_modality(modality):
        out = []
        for part in series:
            dataset = pydicom.dcmread(io.BytesIO(part))
            dataset.Modality = modality
            buffer = io.BytesIO()
            dataset.save_as(buffer)
            out.append(buffer.getvalue())
        return out

    voxels = 24 * 20 * 9
    assert volume_read_cost(with_modality("MR"), "volume.dcm").memory_mb == expected_read_cost(voxels, "mra")[0]
    assert volume_read_cost(series, "volume.dcm").memory_mb == expected_read_cost(voxels, "cta")[0]
    given = volume_read_cost(series, "volume.dcm", reading=VolumeReading(kind="mra"))
    assert given.memory_mb == expected_read_cost(voxels, "mra")[0]
    nifti = volume_read_cost(_nifti(), "v.nii")
    assert nifti.memory_mb == expected_read_cost(nifti.voxels)[0] == max(expected_read_cost(nifti.voxels, "cta")[0],
                                                                         expected_read_cost(nifti.voxels, "mra")[0])
