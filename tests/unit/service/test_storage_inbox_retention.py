"""The DICOM inbox's retention (service/storage/inbox_retention.py) on a real SQLite job store with files on disk."""

from __future__ import annotations

import os
import time

import pytest

from service.storage.blobs import BlobStore
from service.storage.inbox import Inbox
from service.storage.inbox_retention import mark_settled, purge_settled
from service.storage.records import StoredInstance
from service.storage.schema import dimse_instances
from service.storage.store import InputFile, JobRecord, SqlJobStore, new_job_id

HOUR_S = 3600.0
RETENTION_S = 72 * HOUR_S
RECEIVED_AT = time.time() - 10 * HOUR_S  # files and rows of ten hours ago


@pytest.fixture
def node(tmp_path):
    store = SqlJobStore(f"sqlite:///{tmp_path / 'jobs.sqlite3'}")
    yield store, Inbox(store.engine, store.writer), BlobStore(tmp_path / "data")
    store.dispose()


def _receive(inbox: Inbox, blobs: BlobStore, study: str, n: int, state: str = "committed") -> list[StoredInstance]:
    """``n`` instances of ``study`` on disk and in the inbox, received ``RECEIVED_AT``."""
    items = []
    for i in range(n):
        digest, size = blobs.put_bytes(f"{study}/{i}".encode())
        os.utime(blobs.path(digest), (RECEIVED_AT, RECEIVED_AT))
        item = StoredInstance(f"{study}.{i}", study, f"{study}.s", "1.2.840.10008.5.1.4.1.1.12.1", digest, size,
                              "MODALITY", RECEIVED_AT)
        inbox.add(item, "assoc-1", state)
        items.append(item)
    if state == "committed":
        inbox.mark_dispatched(study, [item.sop_instance_uid for item in items])
    return items


def _job_on(store: SqlJobStore, items: list[StoredInstance]) -> str:
    now = time.time()
    inputs = [InputFile(role, item.sha256, item.size, ".dcm") for role, item in zip(("ap", "lat"), items)]
    job = JobRecord(id=new_job_id(), owner="anonymous", status="queued", created_at=now, updated_at=now,
                    max_attempts=2, inputs=inputs)
    return store.create(job)[0].id


def _finish(store: SqlJobStore, job_id: str) -> float:
    claimed = store.claim_job(job_id, "w1", 60.0)
    assert claimed is not None
    store.complete(job_id, "w1", "succeeded", result={})
    return store.get(job_id).finished_at


def _on_disk(blobs: BlobStore) -> set[str]:
    return set(blobs.all_digests())


def test_a_settled_study_goes_after_the_retention_and_its_jobs_files_with_the_job(node):
    store, inbox, blobs = node
    items = _receive(inbox, blobs, "1.2.3", 3)
    refused = _receive(inbox, blobs, "1.2.4", 2)  # dispatched, its job refused: settled at once
    job_id = _job_on(store, items[:2])
    far = time.time() + RETENTION_S + HOUR_S
    assert purge_settled(store.engine, store.writer, blobs, RETENTION_S, now=far).studies == 1  # the refused one
    assert len(inbox.study("1.2.3")) == 3 and inbox.study("1.2.4") == []  # the queued job holds its study
    assert _on_disk(blobs) == {item.sha256 for item in items}
    finished_at = _finish(store, job_id)
    done = purge_settled(store.engine, store.writer, blobs, RETENTION_S, now=finished_at + RETENTION_S - 1.0)
    assert done.rows == 0 and len(inbox.study("1.2.3")) == 3  # finished, but not for the retention yet
    done = purge_settled(store.engine, store.writer, blobs, RETENTION_S, now=finished_at + RETENTION_S + 1.0)
    assert (done.studies, done.rows, done.files) == (1, 3, 1)
    assert inbox.counts() == {} and _on_disk(blobs) == {items[0].sha256, items[1].sha256}  # the job's inputs
    assert store.delete(job_id) == sorted([items[0].sha256, items[1].sha256])  # they go with the job
    assert refused  # (its files went in the first pass)


def test_nothing_goes_before_dispatch_nor_while_the_study_grows(node):
    store, inbox, blobs = node
    waiting = _receive(inbox, blobs, "2.1", 2, state="interrupted")
    _receive(inbox, blobs, "2.2", 2)
    _receive(inbox, blobs, "2.3", 1, state="received")  # its association still open
    more = _receive(inbox, blobs, "2.2.more", 1, state="received")[0]  # 2.2 grows after its dispatch:
    inbox.add(StoredInstance("2.2.9", "2.2", "2.2.s", more.sop_class_uid, more.sha256, more.size, "MODALITY",
                             RECEIVED_AT), "assoc-2", "committed")
    before = _on_disk(blobs)
    far = time.time() + 100 * RETENTION_S
    assert purge_settled(store.engine, store.writer, blobs, RETENTION_S, now=far).rows == 0
    assert _on_disk(blobs) == before and sum(inbox.counts().values()) == 7
    # garbage collection of the job store no longer takes the inbox's files (a study waiting for a volume)
    assert {item.sha256 for item in waiting} <= store.referenced_blobs()


def test_a_crash_between_row_and_file_deletion_is_finished_by_the_next_pass(node):
    store, inbox, blobs = node
    items = _receive(inbox, blobs, "3.1", 3)
    kept = _receive(inbox, blobs, "3.2", 1)  # received after the cutoff: stays
    far = RECEIVED_AT + RETENTION_S + 1.0
    with store.writer.begin() as conn:  # 3.2 arrived later than 3.1
        conn.execute(dimse_instances.update().where(dimse_instances.c.study_uid == "3.2").values(received_at=far))

    class Killed(BaseException):
        pass

    class Crashing:
        """The blob store, killed after deleting one file."""

        def delete(self, digests, *, min_age_seconds):
            blobs.delete(digests[:1], min_age_seconds=min_age_seconds)
            raise Killed("mid-purge")

    assert mark_settled(store.writer, RECEIVED_AT - 1.0) == 0  # nothing settled that early
    with pytest.raises(Killed):
        purge_settled(store.engine, store.writer, Crashing(), RETENTION_S, now=far)
    assert inbox.counts() == {"purging": 3, "dispatched": 1} and len(_on_disk(blobs)) == 3
    assert inbox.study("3.1") == []  # a study being purged is no study of the dispatcher's
    done = purge_settled(store.engine, store.writer, blobs, RETENTION_S, now=far)
    assert (done.rows, done.files) == (3, 2)
    assert inbox.counts() == {"dispatched": 1} and _on_disk(blobs) == {kept[0].sha256}
    assert not {item.sha256 for item in items} & _on_disk(blobs)


def test_a_backlog_goes_a_bounded_number_of_studies_per_pass(node):
    store, inbox, blobs = node
    for study in ("5.1", "5.2", "5.3"):
        _receive(inbox, blobs, study, 2)
    cutoff = time.time() - HOUR_S
    assert mark_settled(store.writer, cutoff, limit=2) == 4 and inbox.counts() == {"purging": 4, "dispatched": 2}
    assert purge_settled(store.engine, store.writer, blobs, HOUR_S).rows == 6  # the two marked, then the third
    assert inbox.counts() == {} and blobs.all_digests() == []
