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


def _assert_heads(engine: sa.Engine, root, cache: bool) -> str:
    """``read_head``: a blob's first bytes (a series' header without its pixels), from the table or the cache."""
    DatabaseBlobStore(root / "api", engine, cache=True)  # the schema
    worker = DatabaseBlobStore(root / "worker", engine, create_schema=False, cache=cache)
    data = bytes(range(256)) * 40
    digest, _ = worker.put_bytes(data)
    assert worker.read_head(digest, 1000) == data[:1000] and worker.read_head(digest, 20_000) == data
    assert worker.read(digest) == data
    with pytest.raises(FileNotFoundError, match="is not stored"):
        worker.read_head("0" * 64, 10)
    return digest


@pytest.mark.parametrize("cache", [True, False])
def test_a_database_blobs_head_is_its_first_bytes(tmp_path, cache):
    _assert_heads(sa.create_engine(f"sqlite:///{tmp_path / 'db.sqlite3'}"), tmp_path, cache)


def test_a_database_blobs_head_on_postgresql(postgres_server, tmp_path):
    engine = sa.create_engine(postgres_server.url, poolclass=sa.pool.NullPool)
    try:
        digest = _assert_heads(engine, tmp_path, cache=False)
        with engine.begin() as conn:  # the session's database is shared with the other scale-out tests
            conn.execute(sa.text("DELETE FROM blob_data WHERE sha256 = :digest"), {"digest": digest})
    finally:
        engine.dispose()


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
