"""The DICOM node inside ``dsareg serve`` (``DSAREG_DICOM_PORT``), with real peers.

dcmtk (``echoscu``, ``storescu``, ``storescp``) and Orthanc's DICOM server send studies and
receive the results; a pynetdicom SCU aborts an association half-way. One server for the
module (stable time 1 s); every registration is the small phantom study with one start.
"""

from __future__ import annotations

import io
import json
import time

import httpx
import numpy as np
import pydicom
import pytest

from dsareg_engine.io.dicom_out import REG_SOP_CLASS, SC_SOP_CLASS, read_registration_matrix
from tests.support.dimse_kit import StoreScp, echoscu, jobs_of_study, need_dcmtk, renamed_study, scu_send, storescu
from tests.support.servers import OrthancServer, free_port
from tests.support.service_testkit import Server, wait_for

STABLE_S = 1.0


def rotation_deg(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(a[:3, :3].T @ b[:3, :3]) - 1) / 2, -1, 1))))


def assert_pose(reg, frame_uid: str, truth: np.ndarray) -> None:
    matrix = read_registration_matrix(reg, frame_uid)
    assert rotation_deg(matrix, truth) < 1.0
    assert np.linalg.norm((matrix - truth) @ np.array([0.0, 0.0, 0.0, 1.0])) < 0.5  # phantom centred on the origin


@pytest.fixture(scope="module")
def node(tmp_path_factory):
    """``dsareg serve`` with its DICOM node; peers: storescu (results to a storescp), Orthanc, a peer that is down."""
    need_dcmtk()
    root = tmp_path_factory.mktemp("dimse")
    dicom_port = free_port()
    orthanc = OrthancServer(dicom_modalities={"dsareg": ["DSAREG", "127.0.0.1", dicom_port]})
    export = StoreScp(root / "storescp")
    peers = [{"ae_title": "STORESCU", "host": "127.0.0.1", "port": export.port},
             {"ae_title": "ORTHANC", "host": "localhost", "port": orthanc.dicom_port},
             {"ae_title": "DOWNPEER", "host": "127.0.0.1", "port": free_port()},  # nothing listens there
             {"ae_title": "ABORTER", "host": "127.0.0.1", "port": free_port()}]
    env = {"DSAREG_DICOM_PORT": str(dicom_port), "DSAREG_DICOM_PEERS": json.dumps(peers),
           "DSAREG_DICOM_STABLE_SECONDS": str(STABLE_S), "DSAREG_DICOM_JOB_OPTIONS": json.dumps({"starts": 1}),
           "DSAREG_DICOM_EXPORT_RETRIES": "2", "DSAREG_DICOM_EXPORT_BACKOFF_SECONDS": "0.2",
           "DSAREG_DICOM_TIMEOUT_SECONDS": "5"}
    server = Server(root / "data", workers=1, env=env).start()
    server.dicom_port, server.orthanc, server.export, server.root = dicom_port, orthanc, export, root
    export.start()
    yield server
    server.stop()
    export.stop()
    orthanc.stop()


def wait_jobs(client, study_uid: str, count: int = 1, timeout: float = 60.0) -> list[dict]:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        found = jobs_of_study(client, study_uid)
        if len(found) >= count:
            return found
        time.sleep(0.1)
    raise AssertionError(f"{count} job(s) of study {study_uid} not queued after {timeout} s")


def test_echo_and_the_association_policy(node):
    assert echoscu(node.dicom_port).returncode == 0
    unknown = echoscu(node.dicom_port, calling="STRANGER")
    assert unknown.returncode != 0 and "Calling AE Title Not Recognized" in unknown.stderr + unknown.stdout
    wrong = echoscu(node.dicom_port, called="NOTDSAREG")
    assert wrong.returncode != 0 and "Called AE Title Not Recognized" in wrong.stderr + wrong.stdout
    other_host = echoscu(node.dicom_port, calling="ORTHANC")  # allowed title, but from 127.0.0.1 == localhost: ok
    assert other_host.returncode == 0


def test_storescu_study_becomes_one_job_and_the_results_reach_storescp(node, study, dciodvfy, tmp_path):
    study_uid, paths = renamed_study(study, tmp_path / "study")
    started = time.monotonic()
    sent = storescu(node.dicom_port, paths)
    sent_s = time.monotonic() - started
    assert sent.returncode == 0, sent.stderr
    with node.client() as client:
        (job,) = wait_jobs(client, study_uid)
        queued_s = time.monotonic() - started - sent_s
        print(f"\nstorescu {len(paths)} instances: {sent_s:.2f} s; job listed {queued_s:.2f} s after the last "
              f"(stable {STABLE_S:g} s)")
        # the target (stable + 2 s) holds when the stable time covers the input parse, which starts at the
        # association's release (benchmarks/dimse.py measures it with the default 10 s); here stable is
        # 1 s and the parse of the volume takes seconds on a loaded machine
        assert queued_s <= STABLE_S + 2.0 + 12.0
        assert job["source"]["dimse"]["calling_ae"] == "STORESCU"
        assert job["source"]["dimse"]["study_uid"] == study_uid
        done = wait_for(client, job["id"], timeout=300)
        assert done["status"] == "succeeded", done
        exported = done["result"]["dicom"]["exported"]
        assert [e["status"] for e in exported] == ["stored"], exported
        # sending the same study again makes no second job (idempotent per study + instances)
        assert storescu(node.dicom_port, paths).returncode == 0
        time.sleep(STABLE_S + 1.5)
        assert len(jobs_of_study(client, study_uid)) == 1
    received = {pydicom.dcmread(p).SOPInstanceUID: p for p in node.export.files()}
    assert set(exported[0]["sop_instance_uids"]) <= set(received)
    reg_uid = done["result"]["dicom"]["instances"]["reg.dcm"]["sop_instance_uid"]
    reg = pydicom.dcmread(received[reg_uid])
    assert reg.SOPClassUID == REG_SOP_CLASS and reg.StudyInstanceUID == study_uid
    assert dciodvfy(received[reg_uid]) == []
    frame = pydicom.dcmread(paths[-1]).FrameOfReferenceUID  # the volume's frame
    assert_pose(reg, frame, study.mesh_to_world)


def test_orthanc_sends_a_study_and_gets_the_reg_back(node, study, tmp_path):
    orthanc = node.orthanc
    try:
        orthanc.start()
    except Exception as exc:  # noqa: BLE001
        pytest.skip(f"cannot start Orthanc ({str(exc)[:200]})")
    study_uid, paths = renamed_study(study, tmp_path / "study")
    auth = (orthanc.user, orthanc.password)
    with httpx.Client(base_url=orthanc.url, auth=auth, timeout=60) as pacs:
        ids = {pacs.post("/instances", content=p.read_bytes()).json()["ParentStudy"] for p in paths}
        (orthanc_study,) = ids
        started = time.monotonic()
        answer = pacs.post("/modalities/dsareg/store", json={"Resources": [orthanc_study], "Synchronous": True})
        assert answer.status_code == 200, answer.text
        sent_s = time.monotonic() - started
        with node.client() as client:
            (job,) = wait_jobs(client, study_uid)
            queued_s = time.monotonic() - started - sent_s
            done = wait_for(client, job["id"], timeout=300)
        finished = time.monotonic()
        assert done["status"] == "succeeded", done
        assert done["result"]["dicom"]["exported"][0]["status"] == "stored"
        reg_uid = done["result"]["dicom"]["instances"]["reg.dcm"]["sop_instance_uid"]
        found = []
        while not found and time.monotonic() - finished < 10:
            found = pacs.post("/tools/find", json={"Level": "Instance", "Query": {"SOPInstanceUID": reg_uid}}).json()
        in_orthanc_s = time.monotonic() - finished
        reg = pydicom.dcmread(io.BytesIO(pacs.get(f"/instances/{found[0]}/file").content))
        classes = [pacs.get(f"/instances/{item['ID']}/simplified-tags").json().get("SOPClassUID")
                   for item in pacs.get(f"/studies/{orthanc_study}/instances").json()]
    print(f"\nOrthanc C-STORE {len(paths)} instances {sent_s:.2f} s, job listed {queued_s:.2f} s later, "
          f"REG found in Orthanc {in_orthanc_s:.2f} s after the job finished")
    assert in_orthanc_s <= 2.0
    assert classes.count(SC_SOP_CLASS) == 2 and classes.count(REG_SOP_CLASS) == 1
    frame = pydicom.dcmread(paths[-1]).FrameOfReferenceUID
    assert_pose(reg, frame, study.mesh_to_world)


def test_aborted_association_leaves_no_job_and_no_files(node, study, tmp_path):
    study_uid, paths = renamed_study(study, tmp_path / "study")
    statuses = scu_send(node.dicom_port, paths, "ABORTER", abort_after=len(paths) - 3)
    assert statuses and set(statuses) == {0}
    time.sleep(STABLE_S + 2.0)
    with node.client() as client:
        assert jobs_of_study(client, study_uid) == []
    import hashlib

    blobs = node.data_dir / "blobs"
    digests = {hashlib.sha256(p.read_bytes()).hexdigest() for p in paths}
    stored = {p.name for p in blobs.glob("??/*")}
    # what the peer sent was stored as sent; none of it is left
    assert not digests & stored
    assert "ended without release" in node.logs()


def test_export_destination_down_fails_clearly_and_the_job_succeeds(node, study, tmp_path):
    study_uid, paths = renamed_study(study, tmp_path / "study")
    assert set(scu_send(node.dicom_port, paths, "DOWNPEER")) == {0}
    with node.client() as client:
        (job,) = wait_jobs(client, study_uid)
        done = wait_for(client, job["id"], timeout=300)
    assert done["status"] == "succeeded", done
    (export,) = done["result"]["dicom"]["exported"]
    assert export["status"] == "failed" and export["attempts"] == 3
    error = export["error"]
    assert error["type"].endswith("/pacs-error") and error["peer"] == "DOWNPEER" and error["step"] == "associate"
    assert "DOWNPEER" in error["detail"] and "3 attempts" in error["detail"]
    assert export["seconds"] < 30
    assert done["result"]["mesh_to_world"]  # the registration itself stands


def _pull_reference(study_uid: str, paths, peer: str) -> dict:
    headers = [pydicom.dcmread(p, stop_before_pixels=True) for p in paths]
    ap, lat = (h for h in headers if h.Modality == "XA")
    volume = next(h for h in headers if h.Modality == "CT")
    return {"source": {"dimse": {"peer": peer, "study_uid": study_uid, "ap": {"series_uid": ap.SeriesInstanceUID},
                                 "lat": {"series_uid": lat.SeriesInstanceUID},
                                 "volume": {"series_uid": volume.SeriesInstanceUID}}},
            "options": {"starts": 1}}


def test_pull_by_dimse_reference_from_orthanc_and_store_back(node, study, tmp_path):
    """``source.dimse``: the worker retrieves the study from Orthanc by C-GET and C-STOREs the results back."""
    orthanc = node.orthanc
    if not orthanc.process or orthanc.process.poll() is not None:
        try:
            orthanc.start()
        except Exception as exc:  # noqa: BLE001
            pytest.skip(f"cannot start Orthanc ({str(exc)[:200]})")
    study_uid, paths = renamed_study(study, tmp_path / "study")
    with httpx.Client(base_url=orthanc.url, auth=(orthanc.user, orthanc.password), timeout=60) as pacs:
        for path in paths:
            assert pacs.post("/instances", content=path.read_bytes()).status_code == 200
        with node.client() as client:
            answer = client.post("/v1/registrations", json=_pull_reference(study_uid, paths, "ORTHANC"))
            assert answer.status_code == 202, answer.text
            done = wait_for(client, answer.json()["id"], timeout=300)
        assert done["status"] == "succeeded", done.get("error")
        dicom = done["result"]["dicom"]
        assert dicom["source"]["dimse"]["peer"] == "ORTHANC" and dicom["source"]["dimse"]["instances"] == len(paths)
        assert dicom["exported"][0]["status"] == "stored"
        reg_uid = dicom["instances"]["reg.dcm"]["sop_instance_uid"]
        found = pacs.post("/tools/find", json={"Level": "Instance", "Query": {"SOPInstanceUID": reg_uid}}).json()
        reg = pydicom.dcmread(io.BytesIO(pacs.get(f"/instances/{found[0]}/file").content))
    print(f"\nC-GET of {len(paths)} instances: {dicom['source']['dimse']['fetch_seconds']:.2f} s")
    assert_pose(reg, pydicom.dcmread(paths[-1]).FrameOfReferenceUID, study.mesh_to_world)


def test_pull_refusals_and_a_retrieve_source_that_is_down(node, study, tmp_path):
    study_uid, paths = renamed_study(study, tmp_path / "study")
    with node.client() as client:
        unknown = client.post("/v1/registrations", json=_pull_reference(study_uid, paths, "NOTAPEER"))
        assert unknown.status_code == 422 and unknown.json()["field"] == "source.dimse.peer"
        bad = _pull_reference(study_uid, paths, "DOWNPEER")
        bad["source"]["dimse"]["study_uid"] = "1.2.x"
        answer = client.post("/v1/registrations", json=bad)
        assert answer.status_code == 422 and answer.json()["field"] == "source.dimse.study_uid"
        answer = client.post("/v1/registrations", json=_pull_reference(study_uid, paths, "DOWNPEER"))
        assert answer.status_code == 202
        done = wait_for(client, answer.json()["id"], timeout=120)
    assert done["status"] == "failed"
    error = done["error"]
    assert error["type"].endswith("/pacs-error") and error["peer"] == "DOWNPEER" and error["step"] == "retrieve ap (C-GET)"
    assert "DOWNPEER" in error["detail"]
