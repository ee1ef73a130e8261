"""``DSAREG_EXPORT_AFTER_REVIEW=true`` against real peers: Orthanc (STOW-RS) and dcmtk's storescp (C-STORE).

One server for the module: the results of a finished job stay out of the PACS until a person
approves it; a rejected job is never exported; a PACS that does not answer gives a ``pacs-error``
after bounded attempts without holding up the review; an API frozen (SIGSTOP) past its export lease
finishes that attempt and starts no other; an API killed (SIGKILL) during the export exports after its restart. Every registration is the small phantom study with one start.
"""

from __future__ import annotations

import json
import os
import signal
import time

import httpx
import pytest

from tests.support.dimse_kit import StoreScp, jobs_of_study, need_dcmtk, renamed_study, storescu
from tests.support.servers import OrthancServer, free_port
from tests.support.service_testkit import Server, wait_for
from tests.support.time_bounds import allowed

RESULTS = ("reg.dcm", "overlay_ap.dcm", "overlay_lat.dcm")
START_S = 240.0  # a worker's start (torch, kernels, warm-up job) on a loaded 2-core machine has taken > 90 s
EXPORT_LEASE_S = 5.0  # (default 15 s) the frozen and the killed API wait for it to lapse: renewed every 1.7 s
FROZEN_S = EXPORT_LEASE_S + 2.0  # the API stays frozen past its export lease


@pytest.fixture(scope="module")
def orthanc(study):
    server = OrthancServer()
    try:
        server.start()
    except Exception as exc:  # noqa: BLE001
        server.stop()
        pytest.skip(f"cannot start Orthanc with the DICOMweb plugin ({str(exc)[:200]})")
    with httpx.Client(base_url=server.url, auth=(server.user, server.password), timeout=30) as client:
        for data in study.instances():
            assert client.post("/instances", content=data).status_code == 200
    yield server
    server.stop()


@pytest.fixture(scope="module")
def node(tmp_path_factory, orthanc):
    need_dcmtk()
    root = tmp_path_factory.mktemp("export-review")
    destination = StoreScp(root / "storescp").start()
    dicom_port = free_port()
    env = {"DSAREG_EXPORT_AFTER_REVIEW": "true", "DSAREG_EXPORT_MAX_ATTEMPTS": "2",
           "DSAREG_EXPORT_LEASE_SECONDS": str(EXPORT_LEASE_S),
           "DSAREG_EXPORT_RETRY_BACKOFF_SECONDS": "0.5",
           "DSAREG_DICOMWEB_SERVERS": json.dumps([{"url": orthanc.dicomweb_url, "username": orthanc.user,
                                                   "password": orthanc.password}]),
           "DSAREG_DICOMWEB_TIMEOUT_SECONDS": "1", "DSAREG_DICOMWEB_RETRIES": "1",
           "DSAREG_DICOMWEB_RETRY_BACKOFF_SECONDS": "0.1",
           "DSAREG_DICOM_PORT": str(dicom_port), "DSAREG_DICOM_STABLE_SECONDS": "1",
           "DSAREG_DICOM_PEERS": json.dumps([{"ae_title": "STORESCU", "host": "127.0.0.1", "port": destination.port}]),
           "DSAREG_DICOM_JOB_OPTIONS": json.dumps({"starts": 1}), "DSAREG_DICOM_TIMEOUT_SECONDS": "5"}
    server = Server(root / "data", workers=1, env=env).start(timeout=START_S)
    server.dicom_port, server.destination = dicom_port, destination
    yield server
    server.stop()
    destination.stop()


@pytest.fixture(scope="module")
def finished(node, orthanc, study):
    """Four jobs by DICOMweb reference (store_results), run to the end while nothing may be exported."""
    reference = {"source": {"dicomweb": {
        "url": orthanc.dicomweb_url, "study_uid": study.study_uid, "ap": {"series_uid": study.uids["ap_series"]},
        "lat": {"series_uid": study.uids["lat_series"]}, "volume": {"series_uid": study.uids["volume_series"]}}},
        "options": {"starts": 1}, "store_results": True}
    with node.client() as client:
        ids = []
        for _ in range(4):
            answer = client.post("/v1/registrations", json=reference)
            assert answer.status_code == 202, answer.text
            ids.append(answer.json()["id"])
        return [wait_for(client, job_id, timeout=400) for job_id in ids]


def in_pacs(orthanc, study_uid: str) -> set[str]:
    """The SOP Instance UIDs Orthanc holds in the study (QIDO-RS)."""
    answer = httpx.get(f"{orthanc.dicomweb_url}/studies/{study_uid}/instances", auth=(orthanc.user, orthanc.password),
                       headers={"Accept": "application/dicom+json"}, timeout=30)
    return {item["00080018"]["Value"][0] for item in answer.json()} if answer.status_code == 200 else set()


def result_uids(job: dict) -> set[str]:
    return {job["result"]["dicom"]["instances"][name]["sop_instance_uid"] for name in RESULTS}


def review(client, job_id: str, decision: str) -> tuple[dict, float]:
    started = time.monotonic()
    answer = client.post(f"/v1/registrations/{job_id}/review", json={"decision": decision, "comment": "checked"})
    assert answer.status_code == 200, answer.text
    return answer.json(), time.monotonic() - started


def export_state(client, job_id: str, states: tuple[str, ...], timeout: float) -> dict:
    return wait_for(client, job_id, timeout=timeout, predicate=lambda job: job["export"]["state"] in states)["export"]


def test_held_until_approved_and_never_after_rejection(node, orthanc, study, finished):
    approved, rejected = finished[0], finished[1]
    for job in finished:
        assert job["status"] == "succeeded", job.get("error")
        assert job["export"]["state"] == "awaiting_review" and job["export"]["via"] == "stow-rs", job["export"]
        assert "stored" not in job["result"]["dicom"] and job["result"]["dicom"]["source"]["study_uid"]
    assert not set().union(*map(result_uids, finished)) & in_pacs(orthanc, study.study_uid)
    with node.client() as client:
        answer, seconds = review(client, approved["id"], "approved")
        assert answer["export"]["state"] == "pending" and seconds < allowed(2.0)
        started = time.monotonic()
        done = export_state(client, approved["id"], ("done", "failed"), timeout=30)
        print(f"\nexport after approval: done {time.monotonic() - started:.2f} s after the answer")
        assert done["state"] == "done" and set(done["sop_instance_uids"]) == result_uids(approved), done
        assert result_uids(approved) <= in_pacs(orthanc, study.study_uid)
        answer, _ = review(client, rejected["id"], "rejected")
        assert answer["export"]["state"] == "skipped"
        time.sleep(3)
        assert client.get(f"/v1/registrations/{rejected['id']}").json()["export"]["state"] == "skipped"
        audit = client.get(f"/v1/registrations/{approved['id']}/audit").json()["items"]
    assert not result_uids(rejected) & in_pacs(orthanc, study.study_uid)
    events = [item["event"] for item in audit]
    assert events[-4:] == ["export_awaiting_review", "reviewed", "export_queued", "exported"], events
    assert audit[-1]["details"]["via"] == "stow-rs" and audit[-1]["actor"] == "service"


def test_a_dimse_study_is_exported_by_c_store_after_approval(node, study, tmp_path):
    study_uid, paths = renamed_study(study, tmp_path / "study")
    assert storescu(node.dicom_port, paths).returncode == 0
    with node.client() as client:
        deadline = time.monotonic() + 60
        while not (found := jobs_of_study(client, study_uid)) and time.monotonic() < deadline:
            time.sleep(0.2)
        job = wait_for(client, found[0]["id"], timeout=400)
        assert job["status"] == "succeeded" and job["export"]["state"] == "awaiting_review", job
        assert job["export"]["via"] == "c-store" and job["export"]["destination"] == "STORESCU"
        assert "exported" not in job["result"]["dicom"]
        time.sleep(1)
        assert node.destination.files() == []  # nothing sent yet
        review(client, job["id"], "approved")
        done = export_state(client, job["id"], ("done", "failed"), timeout=30)
    assert done["state"] == "done", done
    import pydicom

    received = {str(pydicom.dcmread(path).SOPInstanceUID) for path in node.destination.files()}
    assert result_uids(job) <= received


def test_a_pacs_that_does_not_answer_gives_a_pacs_error_without_holding_the_review(node, orthanc, study, finished):
    job = finished[2]
    os.kill(orthanc.process.pid, signal.SIGSTOP)  # connections are accepted, nothing is answered
    try:
        with node.client() as client:
            answer, seconds = review(client, job["id"], "approved")
            assert seconds < allowed(2.0) and answer["export"]["state"] == "pending"
            failed = export_state(client, job["id"], ("failed", "done"), timeout=60)
    finally:
        os.kill(orthanc.process.pid, signal.SIGCONT)
    assert failed["state"] == "failed" and failed["attempts"] == 2, failed
    error = failed["error"]
    assert error["type"].endswith("/pacs-error") and error["status"] == 502, error
    assert orthanc.dicomweb_url in error["detail"] and "STOW-RS" in error["detail"], error
    # (a request sent while Orthanc was stopped may still be read once it runs again: at least once)
    with node.client() as client:  # a new approval tries again, now that the PACS answers
        review(client, job["id"], "approved")
        assert export_state(client, job["id"], ("done", "failed"), timeout=30)["state"] == "done"
    assert result_uids(job) <= in_pacs(orthanc, study.study_uid)


def test_an_api_frozen_past_its_export_lease_finishes_that_attempt_and_no_other(node, study, tmp_path):
    """SIGSTOP of the API (7 s, past its 5 s export lease) while its C-STORE waits on a frozen destination: once
    both resume, the same attempt stores the results; no second attempt starts beside it; exported once."""
    study_uid, paths = renamed_study(study, tmp_path / "study")
    assert storescu(node.dicom_port, paths).returncode == 0
    with node.client() as client:
        deadline = time.monotonic() + 60
        while not (found := jobs_of_study(client, study_uid)) and time.monotonic() < deadline:
            time.sleep(0.2)
        job = wait_for(client, found[0]["id"], timeout=400)
        assert job["status"] == "succeeded" and job["export"]["state"] == "awaiting_review", job
        destination = node.destination.process.pid
        os.kill(destination, signal.SIGSTOP)  # the association request waits for an answer
        try:
            review(client, job["id"], "approved")
            export_state(client, job["id"], ("exporting",), timeout=10)
            os.kill(node.process.pid, signal.SIGSTOP)
            time.sleep(FROZEN_S)
        finally:
            os.kill(destination, signal.SIGCONT)
            time.sleep(0.5)
            os.kill(node.process.pid, signal.SIGCONT)
        done = export_state(client, job["id"], ("done", "failed"), timeout=60)
        events = [item["event"] for item in client.get(f"/v1/registrations/{job['id']}/audit").json()["items"]]
    assert done["state"] == "done" and done["attempts"] == 1, done
    assert events.count("exported") == 1 and "export_retry" not in events, events
    import pydicom

    received = {str(pydicom.dcmread(path).SOPInstanceUID) for path in node.destination.files()}
    assert result_uids(job) <= received


def test_an_api_killed_during_the_export_exports_after_its_restart(node, orthanc, study, finished):
    job = finished[3]
    os.kill(orthanc.process.pid, signal.SIGSTOP)
    try:
        with node.client() as client:
            review(client, job["id"], "approved")
            export_state(client, job["id"], ("exporting",), timeout=10)  # an attempt is under way
        node.kill()  # SIGKILL, the API and its workers, mid-attempt
    finally:
        os.kill(orthanc.process.pid, signal.SIGCONT)
    node.start(timeout=START_S)
    with node.client() as client:
        done = export_state(client, job["id"], ("done", "failed"), timeout=60)
        events = [item["event"] for item in client.get(f"/v1/registrations/{job['id']}/audit").json()["items"]]
    assert done["state"] == "done" and done["attempts"] >= 2, done  # the restarted API took it again
    assert result_uids(job) <= in_pacs(orthanc, study.study_uid)
    assert events.count("exported") == 1 and events.count("export_queued") == 1, events
