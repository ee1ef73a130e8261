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


# ---- DICOM PN: component groups, every value, several scripts (issue 43 item 1) -------------------------------


def _named(uid: str, name, patient_id="P-0042", charset=None):
    ds = pydicom.Dataset()
    ds.SOPClassUID, ds.SOPInstanceUID = "1.2.840.10008.5.1.4.1.1.12.1", uid
    ds.StudyInstanceUID, ds.PatientID, ds.PatientName = "1.2.3", patient_id, name
    if charset:
        ds.SpecificCharacterSet = charset
    return ds


def _through_bytes(ds):
    """The dataset written as a Part 10 file and read back, as an upload or a PACS gives it to the readers."""
    import io

    ds.file_meta = pydicom.dataset.FileMetaDataset()
    ds.file_meta.MediaStorageSOPClassUID, ds.file_meta.MediaStorageSOPInstanceUID = ds.SOPClassUID, ds.SOPInstanceUID
    ds.file_meta.TransferSyntaxUID = pydicom.uid.ExplicitVRLittleEndian
    out = io.BytesIO()
    ds.save_as(out, enforce_file_format=True)
    return identity_of(pydicom.dcmread(io.BytesIO(out.getvalue())))


def test_a_name_in_its_ideographic_group_only_is_a_name_and_is_compared():
    ap = _through_bytes(_named("1.1", "=山田^太郎", charset="ISO_IR 192"))
    lat = _through_bytes(_named("1.2", "=田中^花子", charset=["", "ISO 2022 IR 87"]))
    same = _through_bytes(_named("1.3", "=山田^太郎", charset=["", "ISO 2022 IR 87"]))
    case = case_identity(DicomSources(ap=ap, lat=lat), source="dimse")
    assert case["patient_name"] == "山田, 太郎" and case["mismatch"] == ["patient_name"]
    assert case_identity(DicomSources(ap=ap, lat=same), source="dimse")["mismatch"] == []
    assert "山田, 太郎" in case_search_text(case)


def test_a_mismatch_in_any_component_group_flags_the_pair():
    def mismatch(a, b):
        return case_identity(DicomSources(ap=identity_of(_named("1.1", a)), lat=identity_of(_named("1.2", b))),
                             source="upload")["mismatch"]

    assert mismatch("Yamada^Taro=山田^太郎=やまだ^たろう", "Yamada^Taro=山本^太郎=やまだ^たろう") == ["patient_name"]
    assert mismatch("Yamada^Taro=山田^太郎=やまだ^たろう", "Yamada^Taro=山田^太郎=やまもと^たろう") == ["patient_name"]
    assert mismatch("Yamada^Taro=山田^太郎", "Yamada^Taro") == []  # only the groups both hold are compared
    assert mismatch("=山田^太郎", "Yamada^Taro") == ["patient_name"]  # two names, nothing to compare them by
    assert person_name("Yamada^Taro=山田^太郎=やまだ^たろう") == "Yamada, Taro = 山田, 太郎 = やまだ, たろう"


SAME_PERSON = [  # (as one site writes it, as another does): one patient
    ("Müller^José", "MULLER^jose"), ("Ångström^Zoë", "angstrom^zoe"), ("Straße^Anna", "STRASSE^Anna"),
    ("Doe^Jane^^^", "Doe^Jane"), ("ＹＡＭＡＤＡ^ＴＡＲＯ", "Yamada^Taro"),  # full-width Latin
    ("==ﾔﾏﾀﾞ^ﾀﾛｳ", "==ヤマダ^タロウ"),  # half-width katakana
    ("=홍^길동", "=\u1112\u1169\u11bc^\u1100\u1175\u11af\u1103\u1169\u11bc"),  # Hangul syllables and jamo
    ("=王^小明", "= 王 ^ 小明 "), ("Иванов^Иван", "ИВАНОВ^ИВАН"),
]
OTHER_PERSON = [
    ("Müller^José", "Müller^Josef"), ("==ガク^タロウ", "==カク^タロウ"),  # a dakuten is another kana
    ("=홍^길동", "=홍^길순"), ("=王^小明", "=汪^小明"), ("Иванов^Иван", "Иванова^Ивана"),
    ("Ильин^Йван", "Ильин^Иван"),  # й is not и
]


def test_name_normalisation_in_several_scripts():
    from dsareg_engine.io.case_identity import names_differ

    assert [pair for pair in SAME_PERSON if names_differ(*pair)] == []
    assert [pair for pair in OTHER_PERSON if not names_differ(*pair)] == []


def test_multi_valued_attributes_are_lists_and_every_value_is_compared():
    ds = _named("1.1", r"Doe^John\<b>Evil</b>")
    ds.AccessionNumber = ["A", "B", "C"]
    case = case_identity(DicomSources(ap=identity_of(ds)), source="upload")
    assert case["patient_name"] == ["Doe, John", "<b>Evil</b>"] and case["accession_number"] == ["A", "B", "C"]
    assert "[" not in case_search_text(case) and "'" not in case_search_text(case)
    lat = identity_of(_named("1.2", "Doe^John"))
    assert case_identity(DicomSources(ap=identity_of(ds), lat=lat), source="upload")["mismatch"] == ["patient_name"]
    two_ids = identity_of(_named("1.3", "Doe^John", patient_id=["P-1", "P-2"]))
    assert case_identity(DicomSources(ap=lat, lat=two_ids), source="upload")["mismatch"] == ["patient_id"]
