"""The DICOM inputs' identity, taken by the readers: the same record as a separate parse, the same output bytes."""

from __future__ import annotations

import dataclasses
import itertools

import numpy as np
import pydicom
import pytest
from PIL import Image

from dsareg_engine.io import dicom_out
from dsareg_engine.io.case import load_case
from dsareg_engine.io.dicom_identity import DicomIdentity, DicomSources, identity_of, read_sources


@pytest.fixture(scope="module")
def study():
    from dsareg_engine.simulation.phantom_study import make_biplane_study

    return make_biplane_study(image_px=96, pixel_spacing_mm=1.4, depth=2)


@pytest.fixture(scope="module")
def case(study):
    return load_case(ap=study.ap, ap_name="ap.dcm", lat=study.lat, lat_name="lat.dcm", volume=list(study.volume))


def test_the_case_carries_the_identity_a_separate_parse_finds(study, case):
    again = read_sources(study.ap, study.lat, list(study.volume))  # an independent header parse of the bytes
    assert case.sources == again and not case.sources.unreadable
    ap = pydicom.dcmread(pydicom.filebase.DicomBytesIO(study.ap))
    assert case.sources.ap.sop_instance_uid == str(ap.SOPInstanceUID)
    assert case.sources.ap.study_instance_uid == str(ap.StudyInstanceUID)
    assert [v.sop_instance_uid for v in case.sources.volume] == [
        str(pydicom.dcmread(pydicom.filebase.DicomBytesIO(part)).SOPInstanceUID) for part in study.volume]
    assert case.sources.volume_frame_uid == study.uids["volume_frame"]
    with pytest.raises(dataclasses.FrozenInstanceError):
        case.sources.ap.sop_instance_uid = "1.2"  # type: ignore[misc]


def _outputs(folder, sources: DicomSources, monkeypatch) -> dict[str, bytes]:
    folder.mkdir()
    for name in ("overlay_ap", "overlay_lat"):
        Image.fromarray(np.full((40, 56, 3), 120, np.uint8)).save(folder / f"{name}.png")
    numbers = itertools.count(1)
    monkeypatch.setattr(dicom_out, "new_uid", lambda: f"2.25.{next(numbers)}")  # the random parts, fixed
    monkeypatch.setattr(dicom_out, "_now", lambda: ("20261201", "010203.000000"))
    written = dicom_out.write_dicom_outputs(folder, np.eye(4), sources, folder)
    return {name: (folder / name).read_bytes() for name in written}


def test_outputs_from_the_case_are_byte_equal_to_outputs_from_a_separate_parse(study, case, tmp_path, monkeypatch):
    from_case = _outputs(tmp_path / "case", case.sources, monkeypatch)
    from_parse = _outputs(tmp_path / "parse", read_sources(study.ap, study.lat, list(study.volume)), monkeypatch)
    assert from_case == from_parse and set(from_case) == {"reg.dcm", "overlay_ap.dcm", "overlay_lat.dcm"}
    reg = pydicom.dcmread(tmp_path / "case" / "reg.dcm")
    assert reg.StudyInstanceUID == case.sources.ap.study_instance_uid  # joined the input study


def test_no_sop_uids_no_identity():
    ds = pydicom.Dataset()
    ds.PatientID = "x"
    assert identity_of(ds) is None
    ds.SOPClassUID, ds.SOPInstanceUID = "1.2.3", "1.2.3.4"
    assert identity_of(ds) == DicomIdentity("1.2.3", "1.2.3.4", patient=(("PatientID", "x"),))


def test_non_dicom_images_have_no_identity(build):
    png = build.png(build.dsa(height=64, width=64)[0])
    assert read_sources(png, png, None) == DicomSources()


def test_a_uid_with_several_values_is_unreadable_not_a_list_repr():
    from dsareg_engine.io.dicom_identity import identity_or_none

    ds = pydicom.Dataset()
    ds.SOPClassUID, ds.SOPInstanceUID, ds.StudyInstanceUID = "1.2.840.10008.5.1.4.1.1.12.1", "1.2.9", ["1.2.3", "1.2.4"]
    assert identity_or_none(ds) == (None, True)  # the outputs start a new study instead of writing "['1.2.3', …]"
    ds.StudyInstanceUID = "1.2.3"
    assert identity_or_none(ds)[0].study_instance_uid == "1.2.3"


def _slice_with_comment(build, comment: str) -> bytes:
    """A CT slice whose header carries ``comment`` (Image Comments) before its pixels."""
    import io

    import pydicom

    part = build.ct_series(np.zeros((60, 60, 2), np.float32), np.eye(4))[0]
    dataset = pydicom.dcmread(io.BytesIO(part))
    dataset.ImageComments = comment
    out = io.BytesIO()
    dataset.save_as(out, enforce_file_format=True)
    return out.getvalue()


def _same_header(first, second) -> bool:
    return [(e.tag, e.value) for e in first] == [(e.tag, e.value) for e in second]


def test_a_series_header_from_a_files_first_bytes_is_the_whole_files(build, monkeypatch):
    """:func:`series_header` takes the file's first bytes only where pydicom stopped at the pixel data inside them;
    a header longer than them, or one cut exactly between two elements (pydicom then reads a shorter header with no
    error), is read from the whole file: the same dataset as the whole file's parse in every case."""
    from dsareg_engine.errors import DsaregInputError
    from dsareg_engine.io import dicom_identity
    from dsareg_engine.io.dicom_identity import parse_header, series_header
    from dsareg_engine.io.file_parts import FileParts

    part = _slice_with_comment(build, "x" * 3000)
    comment_at, pixels_at = part.find(b"\x20\x00\x00\x40"), part.find(b"\xe0\x7f\x10\x00")
    assert 0 < comment_at < pixels_at < len(part) - 1000
    whole = parse_header(part, "volume")
    for size, whole_reads in ((pixels_at + 12, 0), (pixels_at + 4, 1), (comment_at, 1), (comment_at + 100, 1),
                              (len(part) + 10, 0)):
        monkeypatch.setattr(dicom_identity, "HEADER_BYTES", size)
        reads = []
        parts = FileParts([lambda: reads.append(1) or part], heads=[lambda n: part[:n]])
        header = series_header(parts, 0, "volume")
        assert _same_header(header, whole) and len(reads) == whole_reads, size
    assert "ImageComments" in whole and "PixelData" not in whole
    monkeypatch.setattr(dicom_identity, "HEADER_BYTES", 64)
    with pytest.raises(DsaregInputError, match="file 0 of the series is empty"):
        series_header(FileParts([lambda: b""], heads=[lambda n: b""]), 0, "volume")
