"""Native XA runs through the HTTP service: accepted by multipart with no geometry, per-view frames,
and refused at submission (422 naming the field) when they cannot be read; whose case they are, from their
headers, as the job and the review page's list carry it (names in ideographic script compared, multi-valued
attributes as lists: issue 43 item 1)."""

from __future__ import annotations

import io
import json
import shutil
import subprocess

import numpy as np
import pydicom
import pytest

from dsareg_engine.metrics import mean_distance_mm
from dsareg_engine.simulation.native_run import to_bytes
from dsareg_engine.simulation.native_run_skull import SkullRunSettings, make_skull_run
from tests.support.service_testkit import needs_engine, wait_for


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    case = make_skull_run(0, SkullRunSettings(size_px=96))
    path = tmp_path_factory.mktemp("mesh") / "tree.obj"
    case.mesh.save(path)
    return case, path.read_bytes()


def _post(client, run, ap: bytes | None = None, lat: bytes | None = None, options: dict | None = None):
    case, mesh = run
    files = [("mesh", ("tree.obj", mesh, "application/octet-stream")),
             ("ap", ("ap.dcm", ap or case.files["ap"], "application/dicom")),
             ("lat", ("lat.dcm", lat or case.files["lat"], "application/dicom"))]
    return client.post("/v1/registrations", files=files, data={"options": json.dumps(options or {})})


def _edited(data: bytes, edit) -> bytes:
    dataset = pydicom.dcmread(io.BytesIO(data))
    edit(dataset)
    return to_bytes(dataset)


@needs_engine
def test_native_runs_register_with_per_view_frames(server, run):
    case, _ = run
    with server.client() as client:
        response = _post(client, run, options={"frames": {"ap": None, "lat": "minip"}})
        assert response.status_code == 202, response.text
        final = wait_for(client, response.json()["id"], timeout=240)
    assert final["status"] == "succeeded", final
    result = final["result"]
    reading = result["image_reading"]
    assert reading["ap"]["run"] == reading["lat"]["run"] == "native"
    assert reading["ap"]["combined"] == "arterial" and reading["lat"]["combined"] == "minip"  # the default: arterial phase
    assert len(reading["ap"]["frame_indices"]) > 1 and reading["ap"]["phase"].startswith("arterial phase")
    add = mean_distance_mm(np.asarray(result["mesh_to_world"]), case.mesh_to_world, case.mesh.vertices)
    assert add < 0.3, add


@needs_engine
def test_unreadable_runs_are_refused_at_submission(server, run):
    case, _ = run

    def no_contrast(dataset):
        frames = dataset.pixel_array.copy()
        frames[:] = frames[0]
        dataset.PixelData = frames.tobytes()

    def missing_mask_frame(dataset):
        dataset.MaskSubtractionSequence[0].MaskFrameNumbers = [1, 12]

    with server.client() as client:
        cases = [({"ap": _edited(case.files["ap"], no_contrast)}, {}, "ap", "contrast"),
                 ({"lat": _edited(case.files["lat"], missing_mask_frame)}, {},
                  "lat.MaskSubtractionSequence[0].MaskFrameNumbers", "does not exist"),
                 ({}, {"frames": {"ap": 0}}, "ap", "not a contrast frame"),
                 ({}, {"frames": {"lat": -1}}, "options.frames.lat", "")]
        for images, options, field, words in cases:
            response = _post(client, run, options=options, **images)
            assert response.status_code == 422, response.text
            body = response.json()
            assert body["field"] == field and words in body["detail"], body


# ---- whose case: names in every script, multi-valued headers (issue 43 item 1) ---------------------------------

STUDY_UID = "1.2.826.0.1.3680043.10.511.43"  # one study for both runs: only the names may differ


def _headed(data: bytes, name: str, charset, accession=None) -> bytes:
    """A run whose PatientName is ``name`` in ``charset`` (written in it, read back by the service)."""
    def edit(dataset):
        dataset.SpecificCharacterSet, dataset.PatientName, dataset.PatientID = charset, name, "P-43"
        dataset.StudyInstanceUID = STUDY_UID
        if accession is not None:
            dataset.AccessionNumber = accession
    return _edited(data, edit)


def _submitted_case(client, run, ap: bytes, lat: bytes) -> tuple[str, dict]:
    """Submit the pair and read its ``case`` (known at submission); the job is canceled at once, so the
    shared worker spends no time on it."""
    response = _post(client, run, ap=ap, lat=lat, options={"starts": 1, "max_iterations": 5})
    assert response.status_code == 202, response.text
    job_id = response.json()["id"]
    assert client.post(f"/v1/registrations/{job_id}/cancel").status_code in (200, 202)
    job = client.get(f"/v1/registrations/{job_id}")
    assert job.status_code == 200 and job.headers["content-type"].startswith("application/json"), job.text
    return job_id, job.json()["case"]


@needs_engine
def test_ideographic_names_of_two_patients_are_flagged(server, run):
    case, _ = run
    yamada = _headed(case.files["ap"], "=山田^太郎", "ISO_IR 192")  # UTF-8
    with server.client() as client:
        other_id, other = _submitted_case(client, run, yamada,
                                          _headed(case.files["lat"], "=田中^花子", ["", "ISO 2022 IR 87"]))
        same_id, same = _submitted_case(client, run, yamada,  # the same name, JIS-encoded by another modality
                                        _headed(case.files["lat"], "=山田^太郎", ["", "ISO 2022 IR 87"]))
        found = [j["id"] for j in client.get("/v1/registrations", params={"q": "山田"}).json()["items"]]
    assert other["patient_name"] == "山田, 太郎" and other["mismatch"] == ["patient_name"], other
    assert same["patient_name"] == "山田, 太郎" and same["mismatch"] == [], same
    assert other_id in found and same_id in found


def _as_the_page_shows(app_js: str, values: list) -> list:
    """``shown()`` of the app.js the server serves, run by node on the values the server sent."""
    line = next((ln for ln in app_js.splitlines() if ln.startswith("const shown = ")), None)
    assert line, "app.js shows header values through shown()"
    script = line + f"console.log(JSON.stringify({json.dumps(values)}.map(shown)));"
    out = subprocess.run(["node", "-e", script], capture_output=True, text=True, timeout=20, check=True).stdout
    return json.loads(out)


@needs_engine
def test_multi_valued_name_and_accession_are_lists(server, run):
    case, _ = run
    name, accession = r"Doe^John\<b>Evil</b>", ["A", "B", "C"]
    with server.client() as client:
        job_id, shown = _submitted_case(client, run, _headed(case.files["ap"], name, "ISO_IR 100", accession),
                                        _headed(case.files["lat"], name, "ISO_IR 100", accession))
        listed = client.get("/v1/registrations", params={"q": "doe, john"})  # the review page's job list
        app_js = client.get("/ui/app.js").text
    assert shown["patient_name"] == ["Doe, John", "<b>Evil</b>"] and shown["accession_number"] == accession, shown
    assert shown["mismatch"] == [], shown
    summary = next(j for j in listed.json()["items"] if j["id"] == job_id)
    assert summary["case"] == shown
    for text in (listed.text, json.dumps(shown)):
        assert "['A'" not in text and "\\\\<b>" not in text and "John, <b>" not in text  # no repr, nothing run together
    if shutil.which("node") is None:
        pytest.skip("node is not installed: the page's rendering of the lists is not run")
    assert _as_the_page_shows(app_js, [shown["patient_name"], shown["accession_number"]]) == [
        "Doe, John; <b>Evil</b>", "A; B; C"]  # one text each (a text node: el() parses no markup)
