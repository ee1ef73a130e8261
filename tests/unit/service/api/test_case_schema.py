"""The case identity as the API and the review page carry it: multi-valued header attributes are lists of
texts (issue 43 item 1), and the page only ever makes text nodes of them."""

from __future__ import annotations

import json
import re
import shutil
import subprocess
from pathlib import Path

import pydicom
import pytest

from dsareg_engine.io.case_identity import case_identity
from dsareg_engine.io.dicom_identity import DicomSources, identity_of
from service.api.schemas.case import case_model

APP_JS = Path(__file__).resolve().parents[4] / "service" / "api" / "ui" / "static" / "app.js"


def _case():
    ds = pydicom.Dataset()
    ds.SOPClassUID, ds.SOPInstanceUID, ds.StudyInstanceUID = "1.2.840.10008.5.1.4.1.1.12.1", "1.1", "1.2.3"
    ds.PatientName, ds.PatientID, ds.AccessionNumber = r"Doe^John\<b>Evil</b>", "P-1", ["A", "B", "C"]
    ds.Modality = "XA"
    return case_identity(DicomSources(ap=identity_of(ds)), source="upload")


def test_multi_valued_case_fields_are_typed_lists():
    model = case_model(_case())
    assert model.patient_name == ["Doe, John", "<b>Evil</b>"] and model.accession_number == ["A", "B", "C"]
    assert json.loads(model.model_dump_json())["inputs"][0]["modality"] == "XA"


def test_review_page_shows_lists_as_text_never_markup():
    source = APP_JS.read_text()
    assert not re.search(r"innerHTML|outerHTML|insertAdjacentHTML|document\.write", source)
    line = next((ln for ln in source.splitlines() if ln.startswith("const shown = ")), None)
    assert line, "app.js shows header values through shown(), lists included"
    if shutil.which("node") is None:
        pytest.skip("node is not installed: the list rendering is not run")
    script = line + 'console.log(JSON.stringify([shown(["A", "B"]), shown("Doe, John"), shown(null)]));'
    out = subprocess.run(["node", "-e", script], capture_output=True, text=True, timeout=20, check=True).stdout
    assert json.loads(out) == ["A; B", "Doe, John", None]


def test_an_image_carried_from_an_earlier_run_is_named_in_the_case_and_the_result():
    """Issue 42: a tracking job sent AP only carries the LAT image of the job that LAT was sent with (followed back
    through earlier one-plane tracks); its case and its result's LAT view name that job."""
    from service.api.routes.tracking import carried_origins as origins
    from service.engine_adapter import job_case
    from service.jobs.worker import carried_images
    from service.storage.records import JobRecord

    first = JobRecord(id="a" * 32, owner="o", status="succeeded", created_at=0.0, updated_at=0.0)
    case, _ = job_case(None, "upload", {"ap": ["ap2.png"], "lat": ["lat.png"]}, carried=origins(first, ("lat",)))
    assert [(row["role"], row.get("carried_from")) for row in case["inputs"]] == [("ap", None), ("lat", "a" * 32)]
    assert case_model(case).inputs[1].carried_from == "a" * 32
    second = JobRecord(id="b" * 32, owner="o", status="succeeded", created_at=0.0, updated_at=0.0, case=case)
    assert origins(second, ("lat",)) == {"lat": "a" * 32}  # the job LAT was sent with, not the one before
    assert origins(second, ("ap",)) == {"ap": "b" * 32}
    result = {"views": {"ap": {"dice": 0.9}, "lat": {"dice": 0.8}}}
    carried_images(result, case)
    assert result["views"] == {"ap": {"dice": 0.9}, "lat": {"dice": 0.8, "image_from_job": "a" * 32}}
    carried_images(result := {"views": {"ap": {}, "lat": {}}}, job_case(None, "upload", {"ap": ["x.png"]})[0])
    assert result["views"] == {"ap": {}, "lat": {}}
