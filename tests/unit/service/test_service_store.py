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
