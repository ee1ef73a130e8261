"""The lease protocol of the job store, on a real SQLite file (fast, no server)."""

from __future__ import annotations

import threading
import time

import pytest

from service.storage.store import ConflictError, InputFile, JobRecord, SqlJobStore, new_job_id


def _job(store: SqlJobStore, key: str | None = None, digest: str = "a" * 64, request_hash: str = "h1", max_attempts=2):
    now = time.time()
    job = JobRecord(id=new_job_id(), owner="anonymous", status="queued", created_at=now, updated_at=now,
                    max_attempts=max_attempts, inputs=[InputFile("mesh", digest, 3, ".obj")],
                    idempotency_key=key, request_hash=request_hash)
    return store.create(job)


@pytest.fixture
def store(tmp_path):
    s = SqlJobStore(f"sqlite:///{tmp_path / 'jobs.sqlite3'}")
    yield s
    s.dispose()


def test_claim_is_exclusive_under_concurrency(store):
    ids = {_job(store)[0].id for _ in range(6)}
    claimed: list[str] = []
    lock = threading.Lock()

    def worker(n):
        while True:
            job = store.claim(f"w{n}", 30)
            if job is None:
                return
            with lock:
                claimed.append(job.id)

    threads = [threading.Thread(target=worker, args=(n,)) for n in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert sorted(claimed) == sorted(ids)  # every job once, none twice


def test_only_the_lease_owner_completes_once(store):
    job, _ = _job(store)
    claimed = store.claim("w1", 30)
    assert claimed.id == job.id and claimed.attempts == 1 and claimed.status == "running"
    assert store.complete(job.id, "intruder", "succeeded", result={}) is False
    assert store.heartbeat(job.id, "intruder", 30) == (False, False)
    assert store.complete(job.id, "w1", "succeeded", result={"ok": 1}, artifacts={"overlay_ap.png": "b" * 64})
    assert store.complete(job.id, "w1", "succeeded", result={"ok": 2}) is False
    final = store.get(job.id)
    assert final.status == "succeeded" and final.result == {"ok": 1}
    assert [e["event"] for e in store.events(job.id)].count("succeeded") == 1


def test_expired_lease_is_retried_then_failed(store):
    job, _ = _job(store, max_attempts=2)
    store.claim("w1", 0.01)
    time.sleep(0.05)
    assert store.recover_expired() == ([job.id], [])
    again = store.claim("w2", 0.01)
    assert again.attempts == 2
    assert store.complete(job.id, "w1", "succeeded") is False  # the presumed-dead worker cannot complete
    time.sleep(0.05)
    assert store.recover_expired() == ([], [job.id])
    final = store.get(job.id)
    assert final.status == "failed" and "2 attempts" in final.error["detail"]


def test_cancel_and_release(store):
    queued, _ = _job(store)
    assert store.request_cancel(queued.id).status == "canceled"
    running, _ = _job(store)
    store.claim("w1", 30)
    flagged = store.request_cancel(running.id)
    assert flagged.status == "running" and flagged.cancel_requested
    assert store.heartbeat(running.id, "w1", 30) == (True, True)
    assert store.release(running.id, "w1")
    assert store.get(running.id).status == "queued" and store.get(running.id).attempts == 0


def test_idempotency_and_delete(store):
    first, created = _job(store, key="k", request_hash="same")
    again, created_again = _job(store, key="k", request_hash="same")
    assert created and not created_again and again.id == first.id
    with pytest.raises(ConflictError):
        _job(store, key="k", request_hash="other")
    other, _ = _job(store, digest="c" * 64)
    assert store.delete(first.id) == ["a" * 64]  # only the blob nobody else references
    assert store.get(first.id) is None and store.get(other.id) is not None


def test_list_pages_with_cursor(store):
    ids = [_job(store)[0].id for _ in range(5)]
    seen, cursor = [], None
    while True:
        page, cursor = store.list(owner="anonymous", status=None, limit=2, cursor=cursor)
        seen += [j.id for j in page]
        if cursor is None:
            break
    assert sorted(seen) == sorted(ids) and len(seen) == 5


def _with_callback(store: SqlJobStore, previous_id: str | None = None) -> JobRecord:
    now = time.time()
    job = JobRecord(id=new_job_id(), owner="k", status="queued", created_at=now, updated_at=now,
                    callback_url="http://127.0.0.1:9/hooks/x", previous_id=previous_id)
    return store.create(job)[0]


def test_callbacks_are_due_only_once_the_job_ended_and_claimed_once(store):
    job = _with_callback(store)
    assert job.callback["state"] == "pending" and job.callback["attempts"] == 0
    assert store.due_callbacks(time.time()) == []  # still queued
    store.request_cancel(job.id)
    assert store.due_callbacks(time.time()) == [job.id]
    row = store.claim_callback(job.id, time.time(), lease_seconds=60)
    assert row["attempts"] == 1 and row["state"] == "delivering"
    assert store.claim_callback(job.id, time.time(), 60) is None  # another deliverer does not get it
    assert store.due_callbacks(time.time()) == []
    store.finish_callback(job.id, 1, state="pending", status_code=503, error="HTTP 503", next_attempt_at=time.time() + 30)
    assert store.due_callbacks(time.time()) == [] and store.due_callbacks(time.time() + 31) == [job.id]
    assert store.get(job.id).callback["last_status"] == 503


def test_an_abandoned_delivery_is_taken_over_and_the_stale_outcome_ignored(store):
    job = _with_callback(store)
    store.request_cancel(job.id)
    first = store.claim_callback(job.id, time.time(), lease_seconds=0.05)  # its deliverer dies
    time.sleep(0.1)
    assert store.due_callbacks(time.time()) == [job.id]
    second = store.claim_callback(job.id, time.time(), lease_seconds=60)
    assert second["attempts"] == 2 and second["delivery_id"] == first["delivery_id"]
    assert not store.finish_callback(job.id, 1, state="failed", status_code=None, error="late", next_attempt_at=None)
    assert store.finish_callback(job.id, 2, state="delivered", status_code=200, error=None, next_attempt_at=None)
    done = store.get(job.id).callback
    assert done["state"] == "delivered" and done["delivered_at"] and done["attempts"] == 2


def test_previous_job_is_read_by_get_and_list_and_deleted_with_the_job(store):
    first = _with_callback(store)
    second = _with_callback(store, previous_id=first.id)
    assert store.get(second.id).previous_id == first.id and store.get(first.id).previous_id is None
    listed = {job.id: job.previous_id for job in store.list(owner="k", status=None, limit=10, cursor=None)[0]}
    assert listed == {first.id: None, second.id: first.id}
    store.delete(second.id)
    assert store.get(second.id) is None and store.due_callbacks(time.time() + 1e6) == []


def _succeeded(store: SqlJobStore, export: dict | None) -> JobRecord:
    job, _ = _job(store, digest=f"{time.time_ns():064x}"[-64:])
    store.claim_job(job.id, "w1", 30)
    assert store.complete(job.id, "w1", "succeeded", result={}, export=export)
    return store.get(job.id)


TARGET = {"via": "stow-rs", "server": "http://127.0.0.1:8042/dicom-web", "study_uid": "1.2.3"}


def test_a_held_export_waits_for_an_approval_and_a_rejection_skips_it(store):
    held, plain = _succeeded(store, TARGET), _succeeded(store, None)
    assert held.export["state"] == "awaiting_review" and held.export["target"] == TARGET and plain.export is None
    assert store.due_exports(time.time()) == []  # not before a review
    store.review(held.id, "rejected", "", "key:1")
    assert store.get(held.id).export["state"] == "skipped" and store.due_exports(time.time()) == []
    store.review(held.id, "approved", "", "key:1")  # the latest review decides
    assert store.get(held.id).export["state"] == "pending" and store.due_exports(time.time()) == [held.id]
    row = store.claim_export(held.id, time.time(), lease_seconds=60)
    assert row["attempts"] == 1 and row["state"] == "exporting" and row["target"] == TARGET
    assert store.claim_export(held.id, time.time(), 60) is None  # one attempt at a time
    store.review(held.id, "rejected", "", "key:1")  # under way: not recalled
    assert store.get(held.id).export["state"] == "exporting"
    assert store.finish_export(held.id, 1, state="done", outcome={"via": "stow-rs", "sop_instance_uids": ["1"]},
                               error=None, next_attempt_at=None)
    events = [e["event"] for e in store.events(held.id)]
    assert events[-7:] == ["export_awaiting_review", "reviewed", "export_skipped", "reviewed", "export_queued",
                           "reviewed", "exported"], events
    done = store.get(held.id).export
    assert done["state"] == "done" and done["done_at"] and done["outcome"]["sop_instance_uids"] == ["1"]


def test_an_abandoned_export_is_taken_over_and_a_rejected_job_is_never_due(store):
    job = _succeeded(store, TARGET)
    store.review(job.id, "approved", "", "key:1")
    store.claim_export(job.id, time.time(), lease_seconds=0.05)  # its API process dies
    time.sleep(0.1)
    assert store.due_exports(time.time()) == [job.id]
    second = store.claim_export(job.id, time.time(), 60)
    assert second["attempts"] == 2
    assert not store.finish_export(job.id, 1, state="failed", outcome=None, error={"detail": "late"}, next_attempt_at=None)
    assert store.finish_export(job.id, 2, state="pending", outcome=None, error={"detail": "refused"},
                               next_attempt_at=time.time() + 30)
    assert store.due_exports(time.time()) == [] and store.due_exports(time.time() + 31) == [job.id]
    assert store.get(job.id).export["last_error"] == {"detail": "refused"}
    store.review(job.id, "rejected", "", "key:1")
    assert store.get(job.id).export["state"] == "skipped" and store.due_exports(time.time() + 1e6) == []
    store.delete(job.id)
    assert store.get(job.id) is None


def test_case_identity_is_stored_and_searched(store):
    plain = _job(store, digest="b" * 64)[0]
    now = time.time()
    job = JobRecord(id=new_job_id(), owner="anonymous", status="queued", created_at=now, updated_at=now,
                    inputs=[InputFile("mesh", "c" * 64, 3, ".obj")], case={"source": "upload", "patient_id": "P_1%"},
                    case_search="p_1% | angio")
    store.create(job)
    assert store.get(job.id).case == {"source": "upload", "patient_id": "P_1%"} and store.get(plain.id).case is None
    found = lambda q: [j.id for j in store.list(owner="anonymous", status=None, limit=10, cursor=None, q=q)[0]]  # noqa: E731
    assert found("P_1%") == [job.id] and found("ANGIO") == [job.id]
    assert found("p%1") == [] and found("px1") == []  # % and _ are literal, not wildcards
    store.set_case(plain.id, {"source": "dicomweb", "patient_id": "Q-7"}, "q-7")
    assert found("q-7") == [plain.id] and store.get(plain.id).case["source"] == "dicomweb"


def test_a_dead_workers_claims_end_at_once_and_only_its_own(store):
    mine, other = _job(store, digest="a" * 64)[0], _job(store, digest="b" * 64)[0]
    store.claim_job(mine.id, "host-123-w0-abc", 30)
    store.claim_job(other.id, "host-1234-w0-def", 30)  # another pid that starts with the same digits
    assert store.recover_expired() == ([], [])  # both leases run for 30 s
    assert store.expire_claims("host-123-w0-") == 1
    assert store.recover_expired() == ([mine.id], [])
    assert store.get(mine.id).status == "queued" and store.get(other.id).status == "running"
    assert [e["event"] for e in store.events(mine.id)][-1] == "lease_expired"


def _lease_until(store: SqlJobStore, job_id: str) -> float:
    import sqlalchemy as sa

    from service.storage.store import job_exports

    with store.engine.connect() as conn:
        return conn.execute(sa.select(job_exports.c.lease_until).where(job_exports.c.job_id == job_id)).scalar_one()


def test_an_export_lease_is_short_and_renewed_while_the_attempt_runs(store, tmp_path):
    from service.jobs.exports import ExportDeliverer
    from service.settings import ServiceSettings
    from service.storage.blobs import BlobStore

    assert ServiceSettings().jobs.export_lease_seconds <= 15.0
    job = _succeeded(store, TARGET)
    store.review(job.id, "approved", "", "key:1")
    seen: list[float] = []

    class SlowPacs(ExportDeliverer):
        def deliver(self, row):  # an attempt that takes 4 leases (the PACS itself is not the point here)
            for _ in range(8):
                time.sleep(0.3)
                seen.append(_lease_until(store, row["job_id"]))
                assert store.due_exports(time.time()) == []  # never looks abandoned while it runs
            store.finish_export(row["job_id"], row["attempts"], state="done", outcome={}, error=None,
                                next_attempt_at=None)
            return "done"

    deliverer = SlowPacs(store, BlobStore(tmp_path), ServiceSettings(data_dir=tmp_path, export_lease_seconds=0.6))
    started = time.time()
    assert deliverer.deliver_due() == 1
    deadline = time.monotonic() + 10
    while store.get(job.id).export["state"] != "done" and time.monotonic() < deadline:
        time.sleep(0.05)
    deliverer._pool.shutdown(wait=True)
    assert store.get(job.id).export["state"] == "done" and len(seen) == 8
    assert max(seen) > started + 2.0  # renewed past the first 0.6 s lease, again and again


def test_a_deliverer_never_claims_what_its_own_pool_still_delivers(store, tmp_path):
    """Its lease lapsed (the API was frozen past it): the attempt that resumes finishes it, no second attempt."""
    import threading

    from service.jobs.exports import ExportDeliverer
    from service.settings import ServiceSettings
    from service.storage.blobs import BlobStore

    job = _succeeded(store, TARGET)
    store.review(job.id, "approved", "", "key:1")
    release = threading.Event()

    class Frozen(ExportDeliverer):
        def renew(self, row, until):  # frozen: no renewal either
            return True

        def deliver(self, row):
            release.wait(10)
            store.finish_export(row["job_id"], row["attempts"], state="done", outcome={}, error=None,
                                next_attempt_at=None)
            return "done"

    deliverer = Frozen(store, BlobStore(tmp_path), ServiceSettings(data_dir=tmp_path, export_lease_seconds=0.3))
    assert deliverer.deliver_due() == 1
    time.sleep(0.5)  # past the lease: the row looks abandoned
    assert store.due_exports(time.time()) == [job.id] and deliverer.deliver_due() == 0
    release.set()
    deliverer._pool.shutdown(wait=True)
    done = store.get(job.id).export
    assert done["state"] == "done" and done["attempts"] == 1


def test_each_concern_stands_alone_on_one_database(tmp_path):
    """Jobs, leases, reviews and deliveries as separate objects on one Database: a job created by one is claimed,
    completed, reviewed and its callback and held export delivered by the others."""
    from service.storage.database import Database
    from service.storage.deliveries import SqlDeliveries
    from service.storage.jobrows import SqlJobs
    from service.storage.leases import SqlLeases
    from service.storage.migrate import upgrade_database
    from service.storage.reviews import SqlReviews

    url = f"sqlite:///{tmp_path / 'jobs.sqlite3'}"
    upgrade_database(url)
    database = Database(url)
    jobs, leases, reviews, deliveries = (kind(database) for kind in (SqlJobs, SqlLeases, SqlReviews, SqlDeliveries))
    now = time.time()
    job, created = jobs.create(JobRecord(id=new_job_id(), owner="a", status="queued", created_at=now, updated_at=now,
                                         inputs=[InputFile("mesh", "a" * 64, 3, ".obj")], callback_url="http://h/cb"))
    assert created and leases.claim("w1", 30).id == job.id
    assert leases.complete(job.id, "w1", "succeeded", result={"ok": 1}, export={"via": "c-store", "peers": ["P"]})
    assert deliveries.due_callbacks(time.time() + 1) == [job.id] and deliveries.due_exports(time.time() + 1) == []
    assert reviews.review(job.id, "approved", "fine", "key:1").export["state"] == "pending"
    assert deliveries.claim_export(job.id, time.time(), 30)["target"] == {"via": "c-store", "peers": ["P"]}
    assert [e["event"] for e in reviews.events(job.id)] == [
        "queued", "claimed", "succeeded", "export_awaiting_review", "reviewed", "export_queued"]
    assert jobs.get(job.id).callback["state"] == "pending" and jobs.ping()
    database.dispose()
