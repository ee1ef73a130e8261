"""PACS exports outside the registration worker (service/jobs/exports.py, issue 43): recorded with the job's
success and due at once, carried out by the API process's exporter with bounded attempts; real SQLite, real
C-STORE associations (an in-process pynetdicom SCP, and a port where nothing listens)."""

from __future__ import annotations

import io
import time

import pytest

from dsareg_engine.io.dicom_out import SC_SOP_CLASS, new_instance, new_uid
from service.jobs.exports import EXPORT_THREADS, ExportDeliverer, export_target
from service.pacs.dicom_jobs import STORED_FILES
from service.settings import ServiceSettings
from service.storage.blobs import BlobStore
from service.storage.store import InputFile, JobRecord, SqlJobStore, new_job_id
from tests.support.servers import free_port


@pytest.fixture
def store(tmp_path):
    s = SqlJobStore(f"sqlite:///{tmp_path / 'jobs.sqlite3'}")
    yield s
    s.dispose()


def _instance() -> bytes:
    ds = new_instance(SC_SOP_CLASS, new_uid())
    ds.PatientID, ds.StudyInstanceUID, ds.SeriesInstanceUID, ds.Modality = "T", new_uid(), new_uid(), "OT"
    buffer = io.BytesIO()
    ds.save_as(buffer, enforce_file_format=True)
    return buffer.getvalue()


def _succeeded(store: SqlJobStore, blobs: BlobStore | None, target: dict | None) -> JobRecord:
    now = time.time()
    job = JobRecord(id=new_job_id(), owner="anonymous", status="queued", created_at=now, updated_at=now,
                    inputs=[InputFile("mesh", f"{time.time_ns():064x}"[-64:], 3, ".obj")])
    store.create(job)
    store.claim_job(job.id, "w1", 30)
    artifacts = {name: blobs.put_bytes(_instance())[0] for name in STORED_FILES} if blobs else {}
    assert store.complete(job.id, "w1", "succeeded", result={}, artifacts=artifacts, export=target)
    return store.get(job.id)


def _settings(tmp_path, peers: list[dict], **values) -> ServiceSettings:
    values = {"dicom_timeout_seconds": 2.0, "dicom_export_retries": 0, "export_retry_backoff_seconds": 0.05, **values}
    return ServiceSettings(data_dir=tmp_path, dicom_peers=peers, **values)


def _drain(deliverer: ExportDeliverer, store: SqlJobStore, job_id: str, until: tuple[str, ...], timeout=20.0,
           attempts: int = 0) -> dict:
    """Run the exporter's rounds until the export is in one of ``until`` after at least ``attempts`` attempts."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        deliverer.deliver_due()
        row = store.get(job_id).export
        if row["state"] in until and row["attempts"] >= attempts:
            return row
        time.sleep(0.05)
    raise AssertionError(f"export of {job_id} not {until} after {timeout} s: {store.get(job_id).export}")


class Scp:
    """A pynetdicom Storage SCP in this process that counts what it stores."""

    def __init__(self, title: str = "LIVE"):
        from pynetdicom import AE, AllStoragePresentationContexts, evt

        self.title, self.port, self.stored = title, free_port(), []
        ae = AE(ae_title=title)
        ae.supported_contexts = AllStoragePresentationContexts
        self.server = ae.start_server(("127.0.0.1", self.port), block=False,
                                      evt_handlers=[(evt.EVT_C_STORE, self._on_store)])

    def _on_store(self, event) -> int:
        self.stored.append(str(event.request.AffectedSOPInstanceUID))
        return 0x0000

    def peer(self) -> dict:
        return {"ae_title": self.title, "host": "127.0.0.1", "port": self.port}


def test_an_export_is_due_when_its_job_succeeds_and_a_rejection_stops_it(store):
    target = {"via": "c-store", "peers": ["P"], "after_review": False}
    job = _succeeded(store, None, target)
    assert job.export["state"] == "pending" and store.due_exports(time.time()) == [job.id]
    assert [e["event"] for e in store.events(job.id)][-2:] == ["succeeded", "export_queued"]
    row = store.claim_export(job.id, time.time(), 60)
    assert row["attempts"] == 1 and row["outcome"] is None
    assert store.finish_export(job.id, 1, state="pending", outcome=None, error={"detail": "refused"},
                               next_attempt_at=time.time())
    assert store.due_exports(time.time() + 1) == [job.id]  # retried…
    store.review(job.id, "rejected", "", "key:1")  # …unless a person rejects the registration meanwhile
    assert store.get(job.id).export["state"] == "skipped" and store.due_exports(time.time() + 1e6) == []
    store.review(job.id, "approved", "", "key:1")  # an approval sends it again
    assert store.due_exports(time.time()) == [job.id]


def test_the_target_says_whether_it_is_held():
    class Dimse:
        def __init__(self):
            self.document = {"export": ["A", "B"]}

    assert export_target(None, Dimse()) == {"via": "c-store", "peers": ["A", "B"], "after_review": False}
    assert export_target(None, Dimse(), after_review=True)["after_review"] is True
    assert export_target(None, None) is None


def test_the_exporter_takes_no_more_than_its_threads_one_per_destination_and_leaves_the_rest_unclaimed(store,
                                                                                                      tmp_path):
    import threading

    release = threading.Event()
    peers = ["P0", "P1", "P2", "P3", "P4", "P0"]  # six jobs, five destinations
    jobs = [_succeeded(store, None, {"via": "c-store", "peers": [peer], "after_review": False}) for peer in peers]

    class Frozen(ExportDeliverer):
        def _attempt(self, row):  # frozen peers: the attempt does not end until released
            release.wait(10)
            store.finish_export(row["job_id"], row["attempts"], state="done", outcome={}, error=None,
                                next_attempt_at=None)
            return "done"

    deliverer = Frozen(store, BlobStore(tmp_path), _settings(tmp_path, []))
    assert deliverer.deliver_due() == EXPORT_THREADS == 4
    assert deliverer.deliver_due() == 0  # full: nothing more is claimed (its lease would lapse in a memory queue)
    states = [store.get(job.id).export["state"] for job in jobs]
    assert states == ["exporting"] * 4 + ["pending"] * 2  # P0's second job waits for P0 even when a thread is free
    release.set()
    for job in jobs:
        assert _drain(deliverer, store, job.id, ("done",))["attempts"] == 1
    deliverer._pool.shutdown(wait=True)


def test_a_frozen_destination_holds_one_thread_and_the_others_exports_go_on(store, tmp_path):
    import threading

    release = threading.Event()
    frozen = [_succeeded(store, None, {"via": "c-store", "peers": ["FROZEN"], "after_review": False}) for _ in range(5)]
    healthy = _succeeded(store, None, {"via": "stow-rs", "server": "http://pacs/dicom-web", "study_uid": "1.2",
                                       "after_review": False})

    class Mixed(ExportDeliverer):
        def _attempt(self, row):
            if row["target"]["via"] == "c-store":
                release.wait(10)
            store.finish_export(row["job_id"], row["attempts"], state="done", outcome={}, error=None,
                                next_attempt_at=None)
            return "done"

    deliverer = Mixed(store, BlobStore(tmp_path), _settings(tmp_path, []))
    assert deliverer.deliver_due() == 2  # one to the frozen peer, the STOW-RS beside it
    assert _drain(deliverer, store, healthy.id, ("done",), timeout=5)["attempts"] == 1
    assert sum(store.get(job.id).export["state"] == "exporting" for job in frozen) == 1
    release.set()
    for job in frozen:
        _drain(deliverer, store, job.id, ("done",))
    deliverer._pool.shutdown(wait=True)


def test_a_dead_peer_fails_after_the_bounded_attempts_with_a_reason(store, tmp_path):
    dead = {"ae_title": "DEAD", "host": "127.0.0.1", "port": free_port()}  # nothing listens there
    blobs = BlobStore(tmp_path / "blobs")
    job = _succeeded(store, blobs, {"via": "c-store", "peers": ["DEAD"], "after_review": False})
    deliverer = ExportDeliverer(store, blobs, _settings(tmp_path, [dead], export_max_attempts=3))
    started = time.monotonic()
    row = _drain(deliverer, store, job.id, ("failed",))
    deliverer._pool.shutdown(wait=True)
    assert row["attempts"] == 3 and time.monotonic() - started < 10
    error = row["last_error"]
    assert error["type"].endswith("/pacs-error") and error["peer"] == "DEAD" and error["step"] == "associate"
    assert "DEAD" in error["detail"] and error["attempts"] == 3
    events = [e["event"] for e in store.events(job.id)]
    assert events[-3:] == ["export_retry", "export_retry", "export_failed"], events


def test_a_retry_goes_only_to_the_destinations_not_yet_stored(store, tmp_path):
    live, down_port = Scp(), free_port()
    try:
        down = {"ae_title": "LATER", "host": "127.0.0.1", "port": down_port}
        blobs = BlobStore(tmp_path / "blobs")
        job = _succeeded(store, blobs, {"via": "c-store", "peers": ["LIVE", "LATER"], "after_review": False})
        settings = _settings(tmp_path, [live.peer(), down], export_max_attempts=5, export_retry_backoff_seconds=0.5)
        deliverer = ExportDeliverer(store, blobs, settings)
        row = _drain(deliverer, store, job.id, ("pending",), attempts=1)
        assert len(live.stored) == 3 and row["last_error"]["peer"] == "LATER"
        later = Scp("LATER")  # the second destination comes up (on its own port: settings name it)
        try:
            deliverer.settings = _settings(tmp_path, [live.peer(), later.peer()], export_max_attempts=5)
            row = _drain(deliverer, store, job.id, ("done",))
        finally:
            later.server.shutdown()
        deliverer._pool.shutdown(wait=True)
    finally:
        live.server.shutdown()
    assert row["attempts"] == 2 and len(live.stored) == 3 and len(later.stored) == 3  # LIVE got each object once
    assert [p["status"] for p in row["outcome"]["peers"]] == ["stored", "stored"]


def test_each_failed_export_attempt_is_one_warning_naming_every_destination(store, tmp_path, caplog):
    """Issue 43 item 7: a failed C-STORE export was logged twice (``dsareg.dimse``: "export to DEAD failed after
    …", then the exporter's "export attempt 1 pending (PACS DEAD: …)"); now one warning per attempt, and a second
    failed destination is named in it (the detail held the first only)."""
    import logging

    dead = [{"ae_title": title, "host": "127.0.0.1", "port": free_port()} for title in ("DEADONE", "DEADTWO")]
    blobs = BlobStore(tmp_path / "blobs")
    job = _succeeded(store, blobs, {"via": "c-store", "peers": ["DEADONE", "DEADTWO"], "after_review": False})
    deliverer = ExportDeliverer(store, blobs, _settings(tmp_path, dead, export_max_attempts=2))
    with caplog.at_level(logging.INFO, logger="dsareg"):
        row = _drain(deliverer, store, job.id, ("failed",))
        deliverer._pool.shutdown(wait=True)
    warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING and r.name.startswith("dsareg")]
    assert len(warnings) == row["attempts"] == 2, warnings
    for number, line in enumerate(warnings, start=1):
        assert line.startswith(f"job {job.id}: export attempt {number} ") and "PACS DEADONE" in line \
            and "PACS DEADTWO" in line, line
    assert "DEADTWO" in row["last_error"]["detail"] and row["last_error"]["peer"] == "DEADONE"
