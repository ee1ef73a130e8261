"""Whose case it is: patient, study and series from the readers' DicomIdentity, as bounded plain text."""

from __future__ import annotations

import pydicom

from dsareg_engine.io.case_identity import (MAX_TEXT, case_identity, case_search_text, dicom_date, person_name,
                                            with_source)
from dsareg_engine.io.dicom_identity import DicomSources, identity_of


def _xa(uid: str, patient_id: str = "P-0042", description: str = "Cerebral angiography", series: str = "AP run"):
    ds = pydicom.Dataset()
    ds.SOPClassUID, ds.SOPInstanceUID = "1.2.840.10008.5.1.4.1.1.12.1", uid
    ds.StudyInstanceUID, ds.SeriesInstanceUID = "1.2.3", uid + ".9"
    ds.PatientName, ds.PatientID = "Doe^Jane^Q", patient_id
    ds.StudyDate, ds.StudyDescription, ds.AccessionNumber = "20261130", description, "A-17"
    ds.Modality, ds.SeriesNumber, ds.SeriesDescription = "XA", 3, series
    return identity_of(ds)


def test_patient_study_and_series_of_each_input():
    sources = DicomSources(ap=_xa("1.1"), lat=_xa("1.2", series="LAT run"))
    case = case_identity(sources, source="dicomweb")
    assert (case["patient_name"], case["patient_id"], case["study_date"]) == ("Doe, Jane Q", "P-0042", "2026-11-30")
    assert (case["study_description"], case["accession_number"], case["study_uid"]) == (
        "Cerebral angiography", "A-17", "1.2.3")
    assert [(i["role"], i["modality"], i["series_number"], i["series_description"], i["instances"])
            for i in case["inputs"]] == [("ap", "XA", "3", "AP run", 1), ("lat", "XA", "3", "LAT run", 1)]
    assert case["source"] == "dicomweb" and case["mismatch"] == []


def test_inputs_of_two_patients_are_named():
    case = case_identity(DicomSources(ap=_xa("1.1"), lat=_xa("1.2", patient_id="P-0099")), source="dimse")
    assert case["mismatch"] == ["patient_id"]


def test_header_text_stays_text_and_bounded():
    payload = '<img src=x onerror="alert(1)">\x00\x1b[31m' + "x" * 300
    case = case_identity(DicomSources(ap=_xa("1.1", description=payload)), source="upload")
    assert case["study_description"].startswith('<img src=x onerror="alert(1)">')  # kept verbatim, as text
    assert len(case["study_description"]) == MAX_TEXT and "\x00" not in case["study_description"]
    assert "\x1b" not in case["study_description"]


def test_uploads_without_dicom_keep_their_file_names():
    case = with_source(None, source="upload", file_names={"mesh": ["vessels.obj"], "ap": ["ap.png"], "lat": ["l.png"]})
    assert case["patient_id"] is None and case["source"] == "upload"
    assert [(i["role"], i["file_names"]) for i in case["inputs"]] == [
        ("ap", ["ap.png"]), ("lat", ["l.png"]), ("mesh", ["vessels.obj"])]
    assert case_search_text(case) is None
    named = with_source(case_identity(DicomSources(ap=_xa("1.1")), source="upload"), source="upload",
                        file_names={"ap": ["run 3.dcm"]})
    assert named["inputs"][0]["file_names"] == ["run 3.dcm"] and named["inputs"][0]["modality"] == "XA"


def test_search_text_and_formats():
    case = case_identity(DicomSources(ap=_xa("1.1")), source="upload")
    assert case_search_text(case) == "p-0042 | doe, jane q | 2026-11-30 | cerebral angiography | a-17"
    assert person_name("Doe") == "Doe" and person_name("^Jane") == "Jane" and person_name(None) is None
    assert dicom_date("2026") == "2026" and dicom_date("20260102") == "2026-01-02"
