"""Crash and restart behaviour of the job machinery, with real servers and real SIGKILLs."""

from __future__ import annotations

import os
import signal
import sqlite3
import time

import pytest

from tests.support.service_testkit import FAST_OPTIONS, Server, needs_engine, submit, wait_for
from tests.support.time_bounds import allowed

# ~4 s on one quiet core (at the case's own 128 px a 2-start job ends in < 1 s, before a stop or a kill lands)
SLOW = {"starts": 8, "max_iterations": 400, "coarse_to_fine": False, "working_size_px": 256}


def _db_rows(data_dir, query, args=()):
    with sqlite3.connect(data_dir / "jobs.sqlite3", timeout=30) as conn:
        return conn.execute(query, args).fetchall()


def _events(data_dir, job_id):
    return [row[0] for row in _db_rows(data_dir, "SELECT event FROM job_events WHERE job_id=? ORDER BY seq", (job_id,))]


@pytest.fixture(scope="module")
def _one_worker_server(tmp_path_factory):
    srv = Server(tmp_path_factory.mktemp("resilience") / "data", workers=1)
    yield srv
    srv.stop()


@pytest.fixture
def one_worker(_one_worker_server):
    """A 1-worker server shared by the tests that need no empty store (each reads only its own job's rows): started
    once; the graceful-stop test stops it, and a test after that one starts it again."""
    if not _one_worker_server.alive():
        _one_worker_server.start()
    return _one_worker_server


@needs_engine
def test_restart_after_server_sigkill_resumes_queued_and_orphaned(tmp_path, example_case):
    data = tmp_path / "data"
    first = Server(data, workers=1).start()
    try:
        with first.client() as c:
            ids = [submit(c, example_case, options={**SLOW, "seed": 0}).json()["id"]]  # the one orphaned mid-run
            # the queued two need not be slow: they only wait behind it (2 slow jobs less to run after the restart)
            ids += [submit(c, example_case, options={**FAST_OPTIONS, "seed": n}).json()["id"] for n in (1, 2)]
            wait_for(c, ids[0], statuses=("running",), timeout=60)
    finally:
        os.killpg(first.process.pid, signal.SIGKILL)  # the whole service, workers included, dies at once
        first.process.wait(10)
        first.log.close()
        first.process = None
    statuses = dict(_db_rows(data, "SELECT id, status FROM jobs"))
    assert statuses[ids[0]] == "running" and statuses[ids[2]] == "queued"

    second = Server(data, workers=2).start()
    try:
        with second.client() as c:
            finals = [wait_for(c, job_id, timeout=240) for job_id in ids]
        assert [f["status"] for f in finals] == ["succeeded"] * 3, finals
        assert finals[0]["attempts"] == 2  # the orphan was claimed again after its lease expired
        for job_id in ids:
            assert _events(data, job_id).count("succeeded") == 1
        assert "lease_expired" in _events(data, ids[0])
    finally:
        second.stop()


@needs_engine
def test_sigkill_worker_mid_job_is_retried_once_to_completion(one_worker, example_case):
    srv = one_worker
    logged_before = len(srv.logs())
    with srv.client() as c:
        job_id = submit(c, example_case, options={"starts": 2, "max_iterations": 300}).json()["id"]
        wait_for(c, job_id, statuses=("running",), timeout=60,
                 predicate=lambda b: (b.get("progress") or {}).get("iteration", 0) > 0)
        (worker_id,) = _db_rows(srv.data_dir, "SELECT worker_id FROM jobs WHERE id=?", (job_id,))[0]
        pid = int(worker_id.split("-")[-3])
        os.kill(pid, signal.SIGKILL)
        final = wait_for(c, job_id, timeout=240)
        assert final["status"] == "succeeded", final
        assert final["attempts"] == 2
        events = _events(srv.data_dir, job_id)
        assert events.count("claimed") == 2 and events.count("succeeded") == 1 and "lease_expired" in events
        deadline = time.monotonic() + allowed(30)  # the supervisor replaced the dead worker (a warm start)
        while c.get("/readyz").status_code != 200 and time.monotonic() < deadline:
            time.sleep(0.5)
        assert c.get("/readyz").status_code == 200
    assert "restarting" in srv.logs()[logged_before:]


@needs_engine
def test_graceful_stop_hands_the_running_job_back(one_worker, example_case):
    srv = one_worker
    try:
        with srv.client() as c:
            job_id = submit(c, example_case, options={**SLOW, "seed": 9}).json()["id"]
            wait_for(c, job_id, statuses=("running",), timeout=60)
    finally:
        srv.stop()  # SIGTERM: uvicorn shuts down, workers stop at their next progress check
    (status, attempts), = _db_rows(srv.data_dir, "SELECT status, attempts FROM jobs WHERE id=?", (job_id,))
    assert (status, attempts) == ("queued", 0)  # back in the queue, no attempt used up
    assert _events(srv.data_dir, job_id)[-1] == "released"
