"""Fast checks of the scale-out pieces that need no servers (SQLite stands in for PostgreSQL)."""

from __future__ import annotations

import io
import time

import pytest
import sqlalchemy as sa

from service.storage.dbblobs import DatabaseBlobStore, make_blob_store
from service.settings import ServiceSettings


@pytest.mark.parametrize("cache", [True, False])
def test_database_blobs_are_shared_without_a_shared_filesystem(tmp_path, cache):
    engine = sa.create_engine(f"sqlite:///{tmp_path / 'db.sqlite3'}")
    api = DatabaseBlobStore(tmp_path / "api", engine, cache=True)
    worker = DatabaseBlobStore(tmp_path / "worker", engine, cache=cache)
    digest, size = api.put_stream(io.BytesIO(b"mesh bytes"))
    assert size == 10 and worker.exists(digest) and worker.read(digest) == b"mesh bytes"
    artifact, _ = worker.put_bytes(b"\x89PNG overlay")
    assert (worker.path(artifact).is_file()) is cache  # workers keep no local copies
    path = api.local_path(artifact)  # the API serves it from its cache, filled from the table
    assert path is not None and path.read_bytes() == b"\x89PNG overlay"
    assert set(api.all_digests()) >= {digest, artifact}
    assert api.delete([digest], min_age_seconds=3600) == 0  # too young
    assert api.delete([digest], min_age_seconds=0) == 1
    assert not worker.exists(digest) and api.local_path(digest) is None
    if not cache:  # (a node's cache may keep content-addressed copies until its own sweep)
        with pytest.raises(FileNotFoundError):
            worker.read(digest)
    time.sleep(0.01)
    assert api.collect_garbage({artifact}, min_age_seconds=0) == 0 and api.exists(artifact)
    assert api.collect_garbage(set(), min_age_seconds=0) == 1 and not api.exists(artifact)


def test_settings_for_scale_out(tmp_path, monkeypatch):
    plain = ServiceSettings(data_dir=tmp_path)
    assert plain.jobs.executor == "embedded" and plain.effective_blob_backend == "files"
    assert type(make_blob_store(plain)).__name__ == "BlobStore"
    monkeypatch.setenv("DSAREG_EXECUTOR", "celery")
    monkeypatch.setenv("DSAREG_BROKER_URL", "redis://broker:6379/1")
    monkeypatch.setenv("DSAREG_JOB_TIMEOUT_SECONDS", "100")
    scaled = ServiceSettings(data_dir=tmp_path)
    assert scaled.celery.broker_url == "redis://broker:6379/1" and scaled.effective_blob_backend == "database"
    assert scaled.effective_visibility_timeout > scaled.jobs.job_timeout_seconds


def test_celery_reliability_settings():
    pytest.importorskip("celery")
    from service.jobs.celery.app import celery_config

    conf = celery_config(ServiceSettings(executor="celery", job_timeout_seconds=600))
    assert conf["task_acks_late"] and conf["task_reject_on_worker_lost"]
    assert conf["worker_prefetch_multiplier"] == 1
    assert conf["broker_transport_options"]["visibility_timeout"] > 600
    assert 600 < conf["task_soft_time_limit"] < conf["task_time_limit"]
