"""What a client codes against: the typed result in the OpenAPI document, and completion callbacks
delivered by a real server to a real HTTP receiver on loopback (signed, retried, at least once)."""

from __future__ import annotations

import hashlib
import hmac
import json
import shutil
import subprocess
import threading
import time
import tomllib
from datetime import datetime
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

import pytest
from tests.support.service_testkit import REPO, Server, needs_engine, wait_for

from tests.support.servers import free_port
from tests.support.time_bounds import allowed

SECRET = "test-secret-of-the-callbacks"


class Receiver:
    """An HTTP server on loopback that records every POST; ``answer`` is its status code, and while
    ``hold`` is set it keeps each request open until ``release`` is set."""

    def __init__(self, port: int | None = None):
        self.port = port or free_port()
        self.requests: list[dict] = []
        self.answer = 204
        self.hold = threading.Event()
        self.release = threading.Event()
        self.arrived = threading.Event()
        self.server: ThreadingHTTPServer | None = None

    def url(self, path: str = "/hooks/done") -> str:
        return f"http://127.0.0.1:{self.port}{path}"

    def start(self) -> Receiver:
        outer = self

        class Handler(BaseHTTPRequestHandler):
            def log_message(self, *args):
                pass

            def do_POST(self):
                body = self.rfile.read(int(self.headers.get("content-length", 0)))
                outer.requests.append({"at": time.time(), "path": self.path, "headers": dict(self.headers),
                                       "body": body})
                outer.arrived.set()
                if outer.hold.is_set():
                    outer.release.wait(60)
                self.send_response(outer.answer)
                self.send_header("content-length", "0")
                self.end_headers()

        self.server = ThreadingHTTPServer(("127.0.0.1", self.port), Handler)
        threading.Thread(target=self.server.serve_forever, daemon=True).start()
        return self

    def stop(self) -> None:
        if self.server is not None:
            self.release.set()
            self.server.shutdown()
            self.server.server_close()
            self.server = None


def documented_check(body: bytes, header: str) -> bool:
    """The receiver's check as docs/api/callbacks.md writes it (Python)."""
    expected = "sha256=" + hmac.new(SECRET.encode(), body, hashlib.sha256).hexdigest()
    return hmac.compare_digest(expected, header)


def epoch(text: str) -> float:
    return datetime.fromisoformat(text.replace("Z", "+00:00")).timestamp()


def callback_env(*receivers: Receiver, timeout: float = 2.0) -> dict[str, str]:
    return {"DSAREG_CALLBACK_ALLOWED": json.dumps([r.url("/hooks/") for r in receivers]),
            "DSAREG_CALLBACK_SECRET": SECRET, "DSAREG_CALLBACK_RETRY_BACKOFF_SECONDS": "0.3",
            "DSAREG_CALLBACK_TIMEOUT_SECONDS": str(timeout)}


@pytest.fixture(scope="module")
def receivers():
    up, later = Receiver().start(), Receiver()  # `later` is down until a test starts it
    yield up, later
    up.stop()
    later.stop()


@pytest.fixture(scope="module")
def contract_server(tmp_path_factory, receivers):
    srv = Server(tmp_path_factory.mktemp("contract") / "data", workers=1, env=callback_env(*receivers)).start()
    yield srv
    srv.stop()


# ---- the typed contract -------------------------------------------------------------------------


def _schema(doc: dict, name: str) -> dict:
    return doc["components"]["schemas"][name]


def _enum(doc: dict, prop: dict) -> list:
    """The enum of a property (through a $ref to a component, and an optional null)."""
    for option in prop.get("anyOf", [prop]):
        if "$ref" in option:
            option = _schema(doc, option["$ref"].rsplit("/", 1)[1])
        if "enum" in option:
            return option["enum"]
    return []


def test_openapi_types_the_whole_result(contract_server):
    with contract_server.client() as c:
        doc = c.get("/openapi.json").json()
    assert doc["info"]["version"] == tomllib.loads((REPO / "pyproject.toml").read_text())["project"]["version"]
    metrics = _schema(doc, "ResultMetrics")["properties"]
    for name, model in (("confidence", "Confidence"), ("initialization", "Initialization"), ("motion", "Motion")):
        assert {"$ref": f"#/components/schemas/{model}"} in metrics[name]["anyOf"], name
    confidence = _schema(doc, "Confidence")
    assert _enum(doc, confidence["properties"]["verdict"]) == ["ok", "check", "failed"]
    assert "verdict" in confidence["required"]
    assert confidence["properties"]["reasons"] == {**confidence["properties"]["reasons"], "type": "array",
                                                   "items": {"type": "string"}}
    signals = _schema(doc, "ConfidenceSignals")["properties"]
    assert signals["dice"]["additionalProperties"] == {"type": "number"}
    assert {"outside_fraction", "border_shift_px", "runner_up", "stopped_on_tolerance"} <= set(signals)
    assert {"type": "number"} in signals["final_step_mm"]["anyOf"]  # a capped final stage's last steps, mm
    for partial in ("unmatched_fraction", "uncovered_fraction"):  # partial visibility, per view 0-1
        assert {"type": "object", "additionalProperties": {"type": "number"}} in signals[partial]["anyOf"], partial
    assert {"type": "boolean"} in signals["partial_loss"]["anyOf"]
    for closed_model in ("Confidence", "ConfidenceSignals", "ResultMetrics", "RegistrationResult", "DicomResult"):
        assert _schema(doc, closed_model).get("additionalProperties") is False, closed_model  # the closed contract
    initialization = _schema(doc, "Initialization")["properties"]
    assert _enum(doc, initialization["method"]) == ["given", "search", "search+coverage", "search+branch",
                                                   "search+coverage+branch", "search+precise"]
    assert {"$ref": "#/components/schemas/CoverageSearch"} in initialization["coverage"]["anyOf"]
    assert {"parts_searched", "best_score", "faces_fraction"} <= set(_schema(doc, "BranchSearch")["properties"])
    assert {"rotation_deg", "translation_mm"} <= set(_schema(doc, "Motion")["required"])
    tracking = _schema(doc, "Tracking")  # tracking over a procedure: either plane alone or both (issue 42)
    assert {"views", "since_reference", "since_previous", "along_beam_measured"} <= set(tracking["required"])
    assert {"$ref": "#/components/schemas/Tracking"} in metrics["tracking"]["anyOf"]
    track_body = doc["paths"]["/v1/registrations/{job_id}/track"]["post"]["requestBody"]["content"]
    assert "required" not in track_body["multipart/form-data"]["schema"]  # ap, lat or both
    result = _schema(doc, "RegistrationResult")["properties"]
    assert _enum(doc, result["verdict"]) == ["ok", "check", "failed"]
    assert {"$ref": "#/components/schemas/DicomResult"} in result["dicom"]["anyOf"]
    assert "sop_instance_uid" in _schema(doc, "DicomInstance")["required"]
    for model in ("JobSummary", "JobStatus"):
        props = _schema(doc, model)["properties"]
        assert props["verdict"]["anyOf"][0] == {"$ref": "#/components/schemas/Verdict"}, model  # one enum type
        assert "succeeded" in props["status"]["description"] and "verdict" in props["status"]["description"]
    assert "`succeeded` means the job ran" in doc["info"]["description"]
    links = _schema(doc, "JobLinks")["properties"]
    assert {"dicom_reg", "dicom_overlay_ap", "dicom_overlay_lat", "dicom_loss", "track", "previous"} <= set(links)
    callback = _schema(doc, "CallbackState")["properties"]
    assert _enum(doc, callback["state"]) == ["pending", "delivering", "delivered", "failed"]
    # both request bodies of the submission, the JSON one as a named model a generator can use
    body = doc["paths"]["/v1/registrations"]["post"]["requestBody"]["content"]
    assert body["application/json"]["schema"]["oneOf"] == [  # by DICOMweb or by DIMSE reference
        {"$ref": "#/components/schemas/DicomwebRegistrationRequest"},
        {"$ref": "#/components/schemas/DimseRegistrationRequest"}]
    for model in ("DicomwebRegistrationRequest", "DimseRegistrationRequest"):
        assert "callback_url" in _schema(doc, model)["properties"]
        assert _schema(doc, model)["additionalProperties"] is False  # the key of `source` tells them apart
    assert _schema(doc, "DimseSource")["properties"]["retrieve"]["enum"] == ["move", "get"]
    assert "callback_url" in body["multipart/form-data"]["schema"]["properties"]
    # authentication is off on this server: no scheme, no lock in /docs
    assert "securitySchemes" not in doc["components"]
    assert not [op for ops in doc["paths"].values() for op in ops.values() if "security" in op]


def test_openapi_declares_bearer_auth_when_keys_are_set(tmp_path):
    srv = Server(tmp_path / "data", workers=0, env={"DSAREG_API_KEYS": "k-123"}).start(wait_ready=False)
    try:
        with srv.client() as c:
            doc = c.get("/openapi.json").json()
    finally:
        srv.stop()
    assert doc["components"]["securitySchemes"]
    assert doc["paths"]["/v1/registrations"]["post"]["security"]


def test_a_json_body_without_source_is_422_naming_source(contract_server):
    with contract_server.client() as c:
        for body, field in (({"options": {}}, "source"), ({}, "source"), ([1, 2], "body")):
            r = c.post("/v1/registrations", json=body)
            assert r.status_code == 422, r.text
            assert r.json()["field"] == field and "Traceback" not in r.text


# ---- callbacks ---------------------------------------------------------------------------------


@pytest.mark.parametrize("url", [
    "http://127.0.0.1:{other}/hooks/done",  # another port
    "http://localhost:{port}/hooks/done",  # another host name
    "https://127.0.0.1:{port}/hooks/done",  # another scheme
    "http://127.0.0.1:{port}/hooksX/done",  # not at a '/' boundary
    "http://127.0.0.1:{port}/hooks/../admin",  # climbing out
    "http://127.0.0.1:{port}/hooks/%2e%2e/admin",
    "http://user@127.0.0.1:{port}/hooks/done",  # user info
    "http://127.0.0.1:{port}@evil.example/hooks/done",
    "ftp://127.0.0.1:{port}/hooks/done",
    "/hooks/done",
])
def test_callback_urls_outside_the_allowed_prefixes_are_422(contract_server, receivers, example_case, url):
    up, _ = receivers
    url = url.format(port=up.port, other=up.port + 1)
    before = len(up.requests)
    with contract_server.client() as c:
        multipart = c.post("/v1/registrations", data={"callback_url": url, "geometry": "paper"},
                           files=[("mesh", ("m.obj", example_case.mesh_obj, "application/octet-stream")),
                                  ("ap", ("ap.png", example_case.ap_png, "image/png")),
                                  ("lat", ("lat.png", example_case.lat_png, "image/png"))])
        reference = c.post("/v1/registrations", json={"callback_url": url, "source": {"dicomweb": {
            "url": "http://127.0.0.1:9/dicom-web", "study_uid": "1.2.3", "ap": {"series_uid": "1.2.3.1"},
            "lat": {"series_uid": "1.2.3.2"}, "volume": {"series_uid": "1.2.3.3"}}}})
    for response in (multipart, reference):
        assert response.status_code == 422, response.text
        problem = response.json()
        assert problem["field"] == "callback_url" and "DSAREG_CALLBACK_ALLOWED" in problem["accepted"], problem
    time.sleep(0.5)
    assert len(up.requests) == before  # nothing was requested


@needs_engine
def test_callback_delivered_signed_within_2_s_of_the_job_end(contract_server, receivers, example_case):
    up, _ = receivers
    up.requests.clear()
    with contract_server.client() as c:
        response = _submit(c, example_case, up.url())
        assert response.status_code == 202, response.text
        job_id = response.json()["id"]
        assert response.json()["callback"]["state"] == "pending"
        final = wait_for(c, job_id, timeout=180)
        assert up.arrived.wait(10), "no callback arrived"
        status = wait_for(c, job_id, predicate=lambda b: b["callback"]["state"] == "delivered", timeout=10)
    assert final["status"] == "succeeded", final
    assert len(up.requests) == 1
    request = up.requests[0]
    delay = request["at"] - epoch(final["finished_at"])
    print(f"callback delay after the job end: {delay:.3f} s")
    assert delay <= allowed(2.0), delay
    headers = {k.lower(): v for k, v in request["headers"].items()}
    assert documented_check(request["body"], headers["x-dsareg-signature"])
    assert not documented_check(request["body"] + b" ", headers["x-dsareg-signature"])
    openssl = shutil.which("openssl")
    if openssl:  # the shell recipe of docs/api/callbacks.md
        digest = subprocess.run([openssl, "dgst", "-sha256", "-hmac", SECRET, "-hex"], input=request["body"],
                                capture_output=True, check=True).stdout.decode().split()[-1]
        assert headers["x-dsareg-signature"] == f"sha256={digest}"
    summary = json.loads(request["body"])
    assert summary["id"] == job_id and summary["status"] == "succeeded"
    assert summary["verdict"] in ("ok", "check", "failed") and summary["verdict"] == final["verdict"]
    assert headers["x-dsareg-delivery"] == status["callback"]["delivery_id"] and headers["x-dsareg-attempt"] == "1"
    assert headers["x-dsareg-job"] == job_id and headers["content-type"] == "application/json"
    assert status["callback"]["attempts"] == 1 and status["callback"]["last_response_status"] == 204


def _submit(c, example_case, callback_url: str):
    return c.post("/v1/registrations", data={"callback_url": callback_url, "geometry": json.dumps(example_case.geometry),
                                             "options": json.dumps({"starts": 1, "max_iterations": 20})},
                  files=[("mesh", ("m.obj", example_case.mesh_obj, "application/octet-stream")),
                         ("ap", ("ap.png", example_case.ap_png, "image/png")),
                         ("lat", ("lat.png", example_case.lat_png, "image/png"))])


def _submit_and_cancel(c, example_case, callback_url: str) -> str:
    """A job that ends quickly however it ends (canceled while queued, or stopped while running)."""
    response = _submit(c, example_case, callback_url)
    assert response.status_code == 202, response.text
    job_id = response.json()["id"]
    assert c.post(f"/v1/registrations/{job_id}/cancel").status_code in (200, 202, 409)
    return job_id


def test_receiver_down_then_up_is_retried_and_delivered(contract_server, receivers, example_case):
    _, later = receivers
    with contract_server.client() as c:
        job_id = _submit_and_cancel(c, example_case, later.url())
        wait_for(c, job_id, timeout=120)
        failing = wait_for(c, job_id, predicate=lambda b: b["callback"]["attempts"] >= 2, timeout=20)
        assert failing["callback"]["state"] in ("pending", "delivering")
        assert failing["callback"]["last_error"] and failing["callback"]["last_response_status"] is None
        later.start()
        done = wait_for(c, job_id, predicate=lambda b: b["callback"]["state"] == "delivered", timeout=30)
    assert len(later.requests) == 1
    headers = {k.lower(): v for k, v in later.requests[0]["headers"].items()}
    assert headers["x-dsareg-delivery"] == done["callback"]["delivery_id"]
    assert int(headers["x-dsareg-attempt"]) == done["callback"]["attempts"] >= 3
    assert documented_check(later.requests[0]["body"], headers["x-dsareg-signature"])
    assert json.loads(later.requests[0]["body"])["status"] in ("canceled", "succeeded")


def test_api_killed_mid_delivery_delivers_after_restart(tmp_path, example_case):
    """At least once: the API dies while the receiver holds the request; the restarted API sends it again
    with the same delivery id."""
    receiver = Receiver().start()
    receiver.hold.set()
    env = callback_env(receiver, timeout=2.0)
    first = Server(tmp_path / "data", workers=0, env=env).start(wait_ready=False)
    try:
        with first.client() as c:
            job_id = _submit_and_cancel(c, example_case, receiver.url())
            assert c.get(f"/v1/registrations/{job_id}").json()["status"] == "canceled"
        assert receiver.arrived.wait(10), "no delivery started"
        first.kill()
        receiver.hold.clear()
        receiver.release.set()
        second = Server(tmp_path / "data", workers=0, env=env).start(wait_ready=False)
        try:
            with second.client() as c:
                done = wait_for(c, job_id, predicate=lambda b: b["callback"]["state"] == "delivered", timeout=30)
        finally:
            second.stop()
    finally:
        first.stop()
        receiver.stop()
    assert len(receiver.requests) == 2
    ids = {r["headers"].get("X-Dsareg-Delivery") for r in receiver.requests}
    assert ids == {done["callback"]["delivery_id"]}
    assert [r["headers"].get("X-Dsareg-Attempt") for r in receiver.requests] == ["1", "2"]
    assert done["callback"]["attempts"] == 2


def test_redirects_are_not_followed(contract_server, receivers, example_case):
    up, _ = receivers
    up.requests.clear()
    up.answer = 307
    try:
        with contract_server.client() as c:
            job_id = _submit_and_cancel(c, example_case, up.url("/hooks/redirect"))
            done = wait_for(c, job_id, predicate=lambda b: b.get("callback", {}).get("state") == "failed", timeout=30)
    finally:
        up.answer = 204
    assert done["callback"]["attempts"] == 1 and "redirect" in done["callback"]["last_error"]
    assert len(up.requests) == 1


# ---- dsareg submit in a pipeline -----------------------------------------------------------------


def _dsareg_submit(server: Server, case_dir: Path, *args: str, swapped: bool = False) -> subprocess.CompletedProcess:
    import os
    import sys

    ap, lat = ("lat.png", "ap.png") if swapped else ("ap.png", "lat.png")
    # a swapped pair fails on its Dice (< 0.1) whether or not the mirror is fitted (2-3 CPU-s): not fitted
    options = {"starts": 1, "max_iterations": 30, **({"mirror_check": False} if swapped else {})}
    command = [sys.executable, "-m", "dsareg_engine.cli", "submit", "--server", server.url, "--mesh",
               str(case_dir / "m.obj"), "--ap", str(case_dir / ap), "--lat", str(case_dir / lat),
               "--geometry", str(case_dir / "geometry.json"), "--options", json.dumps(options), *args]
    return subprocess.run(command, capture_output=True, text=True, timeout=600, cwd=REPO, check=False,
                          env={**os.environ, "PYTHONUNBUFFERED": "1"})


@pytest.fixture(scope="module")
def case_dir(tmp_path_factory, example_case):
    folder = tmp_path_factory.mktemp("submit-case")
    (folder / "m.obj").write_bytes(example_case.mesh_obj)
    (folder / "ap.png").write_bytes(example_case.ap_png)
    (folder / "lat.png").write_bytes(example_case.lat_png)
    (folder / "geometry.json").write_text(json.dumps(example_case.geometry))
    return folder


@needs_engine
def test_submit_in_a_pipe_lines_on_stderr_json_alone_on_stdout_and_dicom_downloaded(contract_server, case_dir,
                                                                                      tmp_path):
    done = _dsareg_submit(contract_server, case_dir, "--out", str(tmp_path / "out"), "--json")
    assert done.returncode == 0, done.stderr[-2000:]
    assert "\r" not in done.stdout and "\r" not in done.stderr
    assert [line for line in done.stderr.splitlines() if line.startswith("progress ")], done.stderr
    assert json.loads(done.stdout)["verdict"] in ("ok", "check", "failed")  # nothing else on stdout
    for name in ("result.json", "overlay_ap.png", "reg.dcm", "overlay_ap.dcm", "overlay_lat.dcm"):
        assert (tmp_path / "out" / name).stat().st_size > 0, name
    import pydicom

    assert pydicom.dcmread(tmp_path / "out" / "reg.dcm").Modality == "REG"


@needs_engine
def test_submit_require_ok_exits_non_zero_on_a_swapped_pair(contract_server, case_dir):
    done = _dsareg_submit(contract_server, case_dir, "--require", "ok", swapped=True)
    assert done.returncode == 3, (done.returncode, done.stdout, done.stderr[-2000:])
    lines = done.stdout.strip().splitlines()
    assert len(lines) == 1 and "verdict failed" in lines[0] and "why: " in lines[0], done.stdout  # the summary alone
    assert "below --require ok" in done.stderr and "\r" not in done.stderr


# ---- the Python client (docs/api/python-client.md) ------------------------------------------------


@needs_engine
def test_python_client_submit_wait_verdict_overlays_dicom_track_cancel(contract_server, receivers, example_case,
                                                                        tmp_path):
    from service.cli.client import RegistrationClient

    up, _ = receivers
    with RegistrationClient(contract_server.url) as client:
        job = client.submit(mesh=example_case.mesh_obj, ap=example_case.ap_png, lat=example_case.lat_png,
                            geometry=example_case.geometry, options={"starts": 1, "max_iterations": 20},
                            callback_url=up.url("/hooks/client"))
        final = client.wait(job["id"], timeout=180)
        assert final["status"] == "succeeded" and final["verdict"] in ("ok", "check")
        assert final["callback"]["url"] == up.url("/hooks/client")
        overlays = client.download_overlays(job["id"], tmp_path)
        assert [p.name for p in overlays] == ["overlay_ap.png", "overlay_lat.png"]
        reg = client.download_dicom(job["id"], "reg.dcm")
        assert reg[128:132] == b"DICM"
        tracked = client.track(job["id"], ap=example_case.ap_png, lat=example_case.lat_png,
                               options={"max_iterations": 10})
        assert tracked["links"]["previous"] == f"/v1/registrations/{job['id']}"
        canceled = client.cancel(tracked["id"])
        assert canceled["status"] in ("canceled", "running")
        assert client.wait(tracked["id"], timeout=120)["status"] in ("canceled", "succeeded")
