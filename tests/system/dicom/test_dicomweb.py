"""DICOMweb in / DICOM out through the service, against a real PACS (Orthanc + DICOMweb plugin).

Orthanc runs on a free loopback port with a temporary storage directory and its own config
(``tests.support.servers.OrthancServer``); without the Debian packages orthanc and
orthanc-dicomweb these tests skip.
"""

from __future__ import annotations

import datetime
import io
import json
import threading
import time
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

import httpx
import numpy as np
import pydicom
import pytest

from dsareg_engine.io.dicom_out import REG_SOP_CLASS, SC_SOP_CLASS, read_registration_matrix
from service.pacs.dicomweb import DicomwebClient, PacsServer
from tests.support.servers import OrthancServer, free_port
from tests.support.service_testkit import Server, forget_generated_client, generated_client, wait_for
from tests.support.time_bounds import allowed

OPTIONS = {"starts": 1}


class Stub:
    """A misbehaving DICOMweb server: ``/slow/...`` answers after 5 s, ``/busy/...`` always 503,
    ``/nostore/...`` forwards reads to ``upstream`` (Orthanc) but answers every STOW with 500."""

    def __init__(self, upstream: str | None = None, auth: tuple[str, str] | None = None):
        self.hits: dict[str, int] = {}
        self.upstream, self.auth = upstream, auth
        stub = self

        class Handler(BaseHTTPRequestHandler):
            def log_message(self, *args):
                pass

            def do_POST(self):
                self.rfile.read(int(self.headers.get("Content-Length", 0)))
                body = b"storage is full"
                self.send_response(500)
                self.send_header("Content-Length", str(len(body)))
                self.end_headers()
                self.wfile.write(body)

            def do_GET(self):
                kind = self.path.split("/")[1]
                stub.hits[kind] = stub.hits.get(kind, 0) + 1
                if kind == "nostore":
                    answer = httpx.get(stub.upstream + self.path[len("/nostore"):], auth=stub.auth,
                                       headers={"Accept": self.headers.get("Accept", "*/*")}, timeout=30)
                    self.send_response(answer.status_code)
                    self.send_header("Content-Type", answer.headers.get("content-type", "application/octet-stream"))
                    self.send_header("Content-Length", str(len(answer.content)))
                    self.end_headers()
                    self.wfile.write(answer.content)
                    return
                if kind == "slow":
                    time.sleep(5)
                self.send_response(503 if kind == "busy" else 200)
                self.send_header("Content-Length", "0")
                self.end_headers()

        self.server = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.server.daemon_threads = True
        self.url = f"http://127.0.0.1:{self.server.server_address[1]}"
        threading.Thread(target=self.server.serve_forever, daemon=True).start()

    def stop(self):
        self.server.shutdown()


@pytest.fixture(scope="module")
def orthanc():
    server = OrthancServer()
    try:
        server.start()
    except Exception as exc:  # noqa: BLE001
        server.stop()
        pytest.skip(f"cannot start Orthanc with the DICOMweb plugin ({str(exc)[:200]}); "
                    "install it: apt-get install orthanc orthanc-dicomweb")
    yield server
    server.stop()


@pytest.fixture(scope="module")
def pacs(orthanc):
    return PacsServer(orthanc.dicomweb_url, orthanc.user, orthanc.password)


@pytest.fixture(scope="module")
def uploaded(orthanc, study):
    """The synthetic study, uploaded to Orthanc through its REST API (as a modality would send it)."""
    with httpx.Client(base_url=orthanc.url, auth=(orthanc.user, orthanc.password), timeout=30) as client:
        for data in study.instances():
            assert client.post("/instances", content=data).status_code == 200
    return study


@pytest.fixture(scope="module")
def stub(orthanc):
    server = Stub(orthanc.dicomweb_url, (orthanc.user, orthanc.password))
    yield server
    server.stop()


@pytest.fixture(scope="module")
def trickler():
    from tests.support.faults_kit import TricklingHttpServer

    server = TricklingHttpServer(interval_s=0.5)  # every read within the 1 s timeout, no answer ever ends
    yield server
    server.close()


PACS_DEADLINE_S = 8.0


@pytest.fixture(scope="module")
def service(tmp_path_factory, orthanc, stub, trickler):
    closed = f"http://127.0.0.1:{free_port()}/dicom-web"  # nothing listens there
    triggering = OrthancServer(password="trigger-test")  # started by the trigger test, with the example's Lua
    servers = [{"url": orthanc.dicomweb_url, "username": orthanc.user, "password": orthanc.password},
               {"url": triggering.dicomweb_url, "username": triggering.user, "password": triggering.password},
               {"url": orthanc.dicomweb_url.replace("/dicom-web", "/bad-credentials"), "username": "x", "password": "y"},
               {"url": closed}, {"url": stub.url + "/slow"}, {"url": stub.url + "/busy"},
               {"url": stub.url + "/nostore"}, {"url": trickler.url}]
    env = {"DSAREG_DICOMWEB_SERVERS": json.dumps(servers), "DSAREG_DICOMWEB_TIMEOUT_SECONDS": "1",
           "DSAREG_DICOMWEB_RETRIES": "2", "DSAREG_DICOMWEB_RETRY_BACKOFF_SECONDS": "0.1",
           "DSAREG_PACS_DEADLINE_SECONDS": str(PACS_DEADLINE_S),
           "DSAREG_EXPORT_MAX_ATTEMPTS": "2", "DSAREG_EXPORT_RETRY_BACKOFF_SECONDS": "0.2"}
    srv = Server(tmp_path_factory.mktemp("dicomweb") / "data", workers=1, env=env).start()
    srv.closed_url = closed
    srv.triggering = triggering
    yield srv
    srv.stop()
    triggering.stop()


def reference(study, url: str, store: bool = True, **changes) -> dict:
    source = {"url": url, "study_uid": study.study_uid, "ap": {"series_uid": study.uids["ap_series"]},
              "lat": {"series_uid": study.uids["lat_series"]}, "volume": {"series_uid": study.uids["volume_series"]}}
    source.update(changes)
    return {"source": {"dicomweb": source}, "options": OPTIONS, "store_results": store}


def rotation_deg(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(a[:3, :3].T @ b[:3, :3]) - 1) / 2, -1, 1))))


def test_register_by_reference_stores_reg_and_overlays_in_the_pacs(service, orthanc, pacs, uploaded, dciodvfy, tmp_path):
    study = uploaded
    with service.client() as client:
        response = client.post("/v1/registrations", json=reference(study, orthanc.dicomweb_url + "/"))
        assert response.status_code == 202, response.text
        job_id = response.json()["id"]
        # the same links as a file submission: only those that lead somewhere now, never null
        assert response.json()["links"] == {"self": f"/v1/registrations/{job_id}",
                                            "cancel": f"/v1/registrations/{job_id}/cancel"}
        job = wait_for(client, job_id, timeout=300)
        assert job["status"] == "succeeded", job
        assert set(job["links"]) == {"self", "result", "overlay_ap", "overlay_lat", "mask_ap", "mask_lat", "loss_plot",
                                     "image_ap", "image_lat", "layers_ap", "layers_lat", "model",
                                     "dicom_reg", "dicom_overlay_ap", "dicom_overlay_lat", "dicom_loss", "track"}
        for name, link in job["links"].items():
            if name != "track":  # a POST
                assert client.get(link).status_code == 200, link
        result = job["result"]
        dicom = result["dicom"]
        assert "stored" not in dicom  # the exporter stores them after the job: the job's export says so
        export = wait_for(client, job_id, timeout=60,
                          predicate=lambda body: body["export"]["state"] in ("done", "failed"))["export"]
        assert export["state"] == "done" and export["via"] == "stow-rs" and export["study_uid"] == study.study_uid
        assert export["destination"] == orthanc.dicomweb_url and not export["after_review"], export
        store_s = (datetime.datetime.fromisoformat(export["done_at"]) -
                   datetime.datetime.fromisoformat(export["last_attempt_at"])).total_seconds()
        # whose case: recorded by the worker from the fetched headers
        assert (job["case"]["source"], job["case"]["patient_id"], job["case"]["study_uid"]) == (
            "dicomweb", "DSAREG-PHANTOM-1", study.study_uid)
        reg_uid = dicom["instances"]["reg.dcm"]["sop_instance_uid"]
        assert set(export["sop_instance_uids"]) == {
            dicom["instances"][n]["sop_instance_uid"] for n in ("reg.dcm", "overlay_ap.dcm", "overlay_lat.dcm")}
        # the service serves the same objects
        served = client.get(f"/v1/registrations/{job['id']}/dicom/reg.dcm")
        assert served.status_code == 200 and served.headers["content-type"] == "application/dicom"
        (tmp_path / "reg.dcm").write_bytes(served.content)
        assert dciodvfy(tmp_path / "reg.dcm") == []
        print(f"\nDICOMweb: fetch {dicom['source']['fetch_seconds']:.3f} s ({dicom['source']['requests']} requests), "
              f"store {store_s:.3f} s (by the exporter, after the job)")
        assert dicom["source"]["fetch_seconds"] + store_s <= 1.5

    # find them in Orthanc by QIDO-RS and read the REG back
    with DicomwebClient(pacs) as client:
        found = httpx.get(f"{orthanc.dicomweb_url}/studies/{study.study_uid}/instances",
                          auth=(orthanc.user, orthanc.password), headers={"Accept": "application/dicom+json"}).json()
        classes = {item["00080018"]["Value"][0]: item["00080016"]["Value"][0] for item in found}
        assert classes[reg_uid] == REG_SOP_CLASS
        assert sum(1 for c in classes.values() if c == SC_SOP_CLASS) == 2
        reg_series = dicom["instances"]["reg.dcm"]["series_instance_uid"]
        reg = pydicom.dcmread(io.BytesIO(client.retrieve_instance(study.study_uid, reg_series, reg_uid)))
    assert reg.SOPClassUID == REG_SOP_CLASS and reg.StudyInstanceUID == study.study_uid
    matrix = read_registration_matrix(reg, study.uids["volume_frame"])
    np.testing.assert_allclose(matrix, np.asarray(result["mesh_to_world"]), rtol=0, atol=1e-9)
    assert rotation_deg(matrix, study.mesh_to_world) < 1.0
    centre = np.array([0.0, 0.0, 0.0, 1.0])  # the phantom is centred on the volume frame's origin
    assert np.linalg.norm((matrix - study.mesh_to_world) @ centre) < 0.5
    assert {s.SeriesInstanceUID for s in reg.ReferencedSeriesSequence} == {
        study.uids["ap_series"], study.uids["lat_series"], study.uids["volume_series"]}


def test_url_not_configured_is_refused_at_submission(service, uploaded):
    with service.client() as client:
        response = client.post("/v1/registrations", json=reference(uploaded, "http://169.254.169.254/dicom-web"))
        assert response.status_code == 422
        assert response.json()["field"] == "source.dicomweb.url"
        bad_uid = reference(uploaded, service.closed_url, study_uid="1.2.3/../../x")
        response = client.post("/v1/registrations", json=bad_uid)
        assert response.status_code == 422 and "study_uid" in response.json()["field"]
        # Idempotency-Key: the same reference twice is one job
        first = client.post("/v1/registrations", json=reference(uploaded, service.closed_url),
                            headers={"Idempotency-Key": "study-1"})
        again = client.post("/v1/registrations", json=reference(uploaded, service.closed_url),
                            headers={"Idempotency-Key": "study-1"})
        assert (first.status_code, again.status_code) == (202, 200) and first.json()["id"] == again.json()["id"]
        assert None not in again.json()["links"].values()  # a replay answers like a file submission's too
        wait_for(client, first.json()["id"], timeout=60)
        # credentials in the request are not accepted (extra fields are refused)
        sneaky = reference(uploaded, service.closed_url)
        sneaky["source"]["dicomweb"]["password"] = "x"
        assert client.post("/v1/registrations", json=sneaky).status_code == 422


@pytest.mark.parametrize("case", ["down", "slow", "busy", "unauthorized", "missing-series"])
def test_pacs_errors_fail_the_job_with_a_clear_reason(service, orthanc, stub, uploaded, case):
    url = {"down": service.closed_url, "slow": stub.url + "/slow", "busy": stub.url + "/busy",
           "unauthorized": orthanc.dicomweb_url.replace("/dicom-web", "/bad-credentials"),
           "missing-series": orthanc.dicomweb_url}[case]
    body = reference(uploaded, url)
    if case == "missing-series":
        body["source"]["dicomweb"]["volume"] = {"series_uid": "1.2.3.4.5"}
    started = time.monotonic()
    with service.client() as client:
        response = client.post("/v1/registrations", json=body)
        assert response.status_code == 202, response.text
        job = wait_for(client, response.json()["id"], timeout=60)
    assert time.monotonic() - started < 30  # bounded: 3 attempts x 1 s timeout + back-off
    assert job["status"] == "failed", job
    error = job["error"]
    assert error["type"].endswith("/pacs-error") and error["server"] == url.rstrip("/")
    assert url.rstrip("/") in error["detail"]
    expected = {"down": (None, 3), "slow": (None, 3), "busy": (503, 3), "unauthorized": (None, 1),
                "missing-series": (404, 1)}[case]
    if case == "unauthorized":  # Orthanc answers 401 or 404 for an unknown root: not retried either way
        assert error.get("http_status") in (401, 404) and error["attempts"] == 1
    else:
        assert (error.get("http_status"), error["attempts"]) == expected, error
    assert error["step"].startswith(("search", "retrieve"))


def test_a_trickling_pacs_frees_the_worker_after_the_jobs_pacs_deadline(service, trickler, uploaded):
    """One byte every 0.5 s: no read ever times out (1 s) and, before the job's PACS budget, each attempt lasted
    10 timeouts, retried twice, for each request of the fetch. Now the job fails once its 8 s are spent."""
    with service.client() as client:
        response = client.post("/v1/registrations", json=reference(uploaded, trickler.url))
        assert response.status_code == 202, response.text
        job = wait_for(client, response.json()["id"], timeout=120)
        events = client.get(f"/v1/registrations/{job['id']}/audit").json()["items"]
    at = {item["event"]: datetime.datetime.fromisoformat(item["at"]).timestamp()
          for item in events}
    held_s = at["failed"] - at["claimed"]
    print(f"\ntrickling PACS: the worker held {held_s:.2f} s (DSAREG_PACS_DEADLINE_SECONDS {PACS_DEADLINE_S:g})")
    assert job["status"] == "failed" and job["error"]["type"].endswith("/pacs-error"), job
    assert "DSAREG_PACS_DEADLINE_SECONDS" in job["error"]["detail"] and trickler.requests >= 1
    assert held_s <= PACS_DEADLINE_S + allowed(3.0), held_s  # the budget, one read timeout, the job's own bookkeeping


def example_lua(dsareg_url: str, dicomweb_url: str, options: str = "{ starts = 1 }") -> str:
    text = (Path(__file__).resolve().parents[3] / "examples" / "pacs" / "orthanc_trigger.lua").read_text()
    for name, value in (("DSAREG", f'"{dsareg_url}"'), ("PACS_DICOMWEB", f'"{dicomweb_url}"'), ("OPTIONS", options)):
        lines = [line for line in text.splitlines() if line.startswith(f"local {name} = ")]
        assert len(lines) == 1, name
        text = text.replace(lines[0], f"local {name} = {value}")
    return text


def test_orthanc_lua_trigger_registers_a_stable_study(service, study, dciodvfy, tmp_path):
    """examples/pacs/orthanc_trigger.lua: upload a study, Orthanc posts the job, dsareg stores the REG back."""
    pacs = service.triggering
    pacs.lua = example_lua(service.url, pacs.dicomweb_url)
    pacs.stable_age = 1
    try:
        pacs.start()
    except Exception as exc:  # noqa: BLE001
        pytest.skip(f"cannot start Orthanc ({str(exc)[:200]})")
    auth = (pacs.user, pacs.password)
    with httpx.Client(base_url=pacs.url, auth=auth, timeout=30) as client:
        for data in study.instances():
            assert client.post("/instances", content=data).status_code == 200
        deadline = time.monotonic() + 240
        reg = None
        while time.monotonic() < deadline and reg is None:
            time.sleep(1)
            try:
                listing = client.get("/series", params={"expand": ""}).json()
            except httpx.TransportError:  # Orthanc may drop a kept-alive connection
                continue
            for series in listing:
                if series["MainDicomTags"].get("Modality") == "REG":
                    reg = client.get(f"/instances/{series['Instances'][0]}/file").content
        assert reg is not None, pacs.logs()[-3000:]
        time.sleep(pacs.stable_age + 2)  # the stored results make the study stable again: no second job
        modalities = [s["MainDicomTags"].get("Modality") for s in client.get("/series", params={"expand": ""}).json()]
    assert sorted(modalities) == ["CT", "OT", "REG", "XA", "XA"], modalities
    (tmp_path / "reg.dcm").write_bytes(reg)
    assert dciodvfy(tmp_path / "reg.dcm") == []
    matrix = read_registration_matrix(pydicom.dcmread(io.BytesIO(reg)), study.uids["volume_frame"])
    assert rotation_deg(matrix, study.mesh_to_world) < 1.0
    assert np.linalg.norm((matrix - study.mesh_to_world)[:3, 3]) < 0.5
    assert "dsareg: registration requested" in pacs.logs()
    assert "already registered, skipped" in pacs.logs()


def test_a_store_failure_is_the_exports_the_job_succeeds_with_its_pose(service, stub, uploaded):
    """The PACS refuses the STOW-RS: the job succeeded (its registration is stored), the export fails with a clear
    pacs-error after its bounded attempts (2 here, DSAREG_EXPORT_MAX_ATTEMPTS)."""
    with service.client() as client:
        response = client.post("/v1/registrations", json=reference(uploaded, stub.url + "/nostore"))
        assert response.status_code == 202, response.text
        job = wait_for(client, response.json()["id"], timeout=300)
        assert job["status"] == "succeeded", job
        export = wait_for(client, job["id"], timeout=60,
                          predicate=lambda body: body["export"]["state"] in ("done", "failed"))["export"]
    assert export["state"] == "failed" and export["attempts"] == 2 and export["via"] == "stow-rs", export
    error = export["error"]
    assert error["step"] == "store results (STOW-RS)" and error["http_status"] == 500 and error["attempts"] == 2
    assert "storage is full" in error["detail"]
    pose = np.asarray(job["result"]["mesh_to_world"])
    assert rotation_deg(pose, uploaded.mesh_to_world) < 1.0


def test_uploaded_dicom_case_gets_the_same_dicom_results(service, study, dciodvfy, tmp_path):
    """The same study as a multipart upload: the DICOM results carry the inputs' patient and study."""
    files = [("ap", ("ap.dcm", study.ap, "application/dicom")), ("lat", ("lat.dcm", study.lat, "application/dicom"))]
    files += [("volume", (f"v{i:03d}.dcm", part, "application/dicom")) for i, part in enumerate(study.volume)]
    with service.client() as client:
        response = client.post("/v1/registrations", files=files, data={"options": json.dumps(OPTIONS)})
        assert response.status_code == 202, response.text
        job = wait_for(client, response.json()["id"], timeout=300)
        assert job["status"] == "succeeded", job
        assert "stored" not in job["result"]["dicom"]
        for name in ("reg.dcm", "overlay_ap.dcm", "overlay_lat.dcm", "loss.dcm"):
            served = client.get(f"/v1/registrations/{job['id']}/dicom/{name}")
            assert served.status_code == 200, name
            (tmp_path / name).write_bytes(served.content)
            assert dciodvfy(tmp_path / name) == [], name
        assert client.get(f"/v1/registrations/{job['id']}/dicom/other.dcm").status_code == 422
    reg = pydicom.dcmread(tmp_path / "reg.dcm")
    assert reg.StudyInstanceUID == study.study_uid and reg.PatientID == "DSAREG-PHANTOM-1"
    matrix = read_registration_matrix(reg, study.uids["volume_frame"])
    np.testing.assert_allclose(matrix, np.asarray(job["result"]["mesh_to_world"]), rtol=0, atol=1e-9)


def test_generated_client_submits_by_reference_and_reads_the_verdict(service, orthanc, uploaded, tmp_path):
    """The JSON body is in /openapi.json: a generated client builds it from typed models and reads the
    verdict from typed fields."""
    import importlib

    with service.client() as client:
        package = generated_client(client.get("/openapi.json").text, tmp_path)
    try:
        submit = importlib.import_module("dsareg_client.api.registrations.submit")
        get_job = importlib.import_module("dsareg_client.api.registrations.get_job")
        models = importlib.import_module("dsareg_client.models")
        api = package.Client(base_url=service.url, raise_on_unexpected_status=True)
        body = models.DicomwebRegistrationRequest.from_dict(reference(uploaded, orthanc.dicomweb_url, store=False))
        assert isinstance(body.source.dicomweb, models.DicomwebSource)
        accepted = submit.sync_detailed(client=api, body=body)
        assert accepted.status_code == 202, accepted.content[:500]
        job_id = accepted.parsed.id
        deadline = time.monotonic() + 300
        while (job := get_job.sync(client=api, job_id=job_id)).status.value in ("queued", "running"):
            assert time.monotonic() < deadline
            time.sleep(0.3)
        assert job.status.value == "succeeded", job.error
        assert job.verdict in list(models.Verdict) and job.result.verdict == job.verdict
        assert job.result.metrics.confidence.verdict == job.verdict
        assert job.result.metrics.initialization.method in list(models.InitializationMethod)
        reg = job.result.dicom.instances["reg.dcm"]
        assert isinstance(reg, models.DicomInstance) and reg.sop_instance_uid
        assert isinstance(job.result.dicom.source, models.DicomSource)
        assert job.result.dicom.source.study_uid == uploaded.study_uid
    finally:
        forget_generated_client(tmp_path)


def _series_uid(data: bytes) -> str:
    return pydicom.dcmread(io.BytesIO(data), stop_before_pixels=True).SeriesInstanceUID


def test_a_cta_series_by_reference_is_read_as_cta(service, orthanc):
    """A CTA head (skull, skull base) and its XA pair in the PACS: the worker reads the referenced series as a CTA;
    read as already subtracted it keeps the head and the job fails naming the volume (never a wrong ok)."""
    from dsareg_engine.simulation.synthetic_volumes import make_volume_case

    case = make_volume_case("cta", "b", voxel_mm=1.2, depth=2, image_px=160, pixel_spacing_mm=0.9,
                            min_head_mm=(30.0, 30.0, 40.0))
    with httpx.Client(base_url=orthanc.url, auth=(orthanc.user, orthanc.password), timeout=30) as client:
        for data in (case.ap, case.lat, *case.volume.parts):
            assert client.post("/instances", content=data).status_code == 200
    source = {"url": orthanc.dicomweb_url, "study_uid": case.volume.study_uid,
              "ap": {"series_uid": _series_uid(case.ap)}, "lat": {"series_uid": _series_uid(case.lat)},
              "volume": {"series_uid": _series_uid(case.volume.parts[0])}}
    options = {**OPTIONS, "initialization": "given", "initial_mesh_to_world": np.eye(4).tolist(),
               "ground_truth_mesh_to_world": case.mesh_to_world.tolist()}
    with service.client() as client:
        good = client.post("/v1/registrations", json={"source": {"dicomweb": source}, "options": options,
                                                      "store_results": False})
        bad = client.post("/v1/registrations", json={"source": {"dicomweb": source}, "store_results": False,
                                                     "options": {**options, "volume_kind": "3d-dsa"}})
        assert good.status_code == 202 and bad.status_code == 202, (good.text, bad.text)
        job = wait_for(client, good.json()["id"], timeout=300)
        failed = wait_for(client, bad.json()["id"], timeout=300)
    assert job["status"] == "succeeded", job
    assert job["result"]["volume"]["kind"] == "cta" and job["result"]["volume"]["voxels_kept"] > 100
    assert job["result"]["metrics"]["ground_truth"]["add_mm"] < 1.0, job["result"]["metrics"]["ground_truth"]
    assert failed["status"] == "failed", failed
    assert "far more than vessels" in json.dumps(failed["error"]) and "volume" in json.dumps(failed["error"])
