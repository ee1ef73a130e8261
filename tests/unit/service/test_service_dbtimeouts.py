"""Deadlines on the job database and the broker (service/storage/dbtimeouts.py, jobs/celery/app.py)."""

from __future__ import annotations

import sqlite3
import time

import pytest
import sqlalchemy as sa

from service.jobs.celery.app import make_celery, publisher_config
from service.settings import ServiceSettings
from service.storage.dbtimeouts import StoreTimeouts
from service.storage.store import InputFile, JobRecord, SqlJobStore, new_job_id, store_for


def test_a_held_sqlite_write_lock_fails_writes_after_the_busy_timeout(tmp_path):
    """Another process in a write transaction (e.g. a frozen worker): writes fail in ~busy_s, reads go on."""
    url = f"sqlite:///{tmp_path / 'jobs.sqlite3'}"
    store = SqlJobStore(url, timeouts=StoreTimeouts(busy_s=0.3))
    holder = sqlite3.connect(tmp_path / "jobs.sqlite3", isolation_level=None)
    holder.execute("BEGIN IMMEDIATE")
    try:
        now = time.time()
        job = JobRecord(id=new_job_id(), owner="a", status="queued", created_at=now, updated_at=now,
                        inputs=[InputFile("mesh", "a" * 64, 3, ".obj")])
        started = time.monotonic()
        with pytest.raises(sa.exc.OperationalError):
            store.create(job)
        assert time.monotonic() - started < 1.0
        started = time.monotonic()
        assert store.ping() is False and time.monotonic() - started < 1.0
        assert store.queued_count() == 0  # reads are not blocked (WAL)
    finally:
        holder.rollback()
        holder.close()
        store.dispose()


def test_settings_reach_the_store(tmp_path):
    settings = ServiceSettings(data_dir=tmp_path, sqlite_busy_timeout_seconds=0.7, db_statement_timeout_seconds=2.0)
    store = store_for(settings)
    try:
        assert store.timeouts.busy_s == 0.7 and store.timeouts.statement_s == 2.0
        with store.engine.connect() as conn:
            assert conn.exec_driver_sql("PRAGMA busy_timeout").scalar() == 700
    finally:
        store.dispose()


def test_publisher_waits_are_bounded_by_the_publish_budget():
    settings = ServiceSettings(executor="celery", broker_publish_timeout_seconds=0.5)
    conf = publisher_config(settings)
    options = conf["broker_transport_options"]
    attempts = 1 + conf["task_publish_retry_policy"]["max_retries"]
    # each attempt: at most one connect and one command, each bounded by the socket timeouts
    assert attempts * (options["socket_connect_timeout"] + options["socket_timeout"]) <= 1.0 + 1e-9
    assert options["visibility_timeout"] > 0  # the worker-side options are kept
    api_side = make_celery(settings)
    assert api_side.conf.broker_transport_options["socket_timeout"] == options["socket_timeout"]
    worker_side = make_celery(settings, task=lambda self, job_id: None)
    assert "socket_timeout" not in worker_side.conf.broker_transport_options  # long BRPOP polls stay
