"""Faults injected into the single-machine topology (API + embedded worker processes, SQLite).

Each test asserts the suite's invariants: 0 jobs lost, 0 stuck, 0 run twice to completion,
the next POST answered within 1 s, and no process of the server left running after it stopped.
"""

from __future__ import annotations

import os
import signal
import sqlite3
import time

import pytest
from tests.support.faults_kit import (
    MULTIPART_START,
    NEXT_POST_SECONDS,
    descendants,
    partial_multipart,
    running,
    settle,
    tally,
    timed_post,
    wait_gone,
)
from tests.support.service_testkit import Server, needs_engine, submit, wait_for
from tests.support.time_bounds import allowed

pytestmark = [needs_engine, pytest.mark.slow]

FAST = {"starts": 1, "max_iterations": 10}
SLOW = {"starts": 8, "max_iterations": 400, "coarse_to_fine": False}  # on slow_case


def _rows(data_dir, query, args=()):
    with sqlite3.connect(data_dir / "jobs.sqlite3", timeout=30) as conn:
        return conn.execute(query, args).fetchall()


def _events(data_dir):
    return lambda job_id: [r[0] for r in _rows(data_dir, "SELECT event FROM job_events WHERE job_id=? ORDER BY seq",
                                               (job_id,))]


def _status(data_dir):
    def status_of(job_id: str) -> str:
        rows = _rows(data_dir, "SELECT status FROM jobs WHERE id=?", (job_id,))
        return rows[0][0] if rows else "missing"
    return status_of


def _worker_pids(srv: Server) -> list[int]:
    """Live embedded worker processes (their pids are in the workers heartbeat table)."""
    known = {pid for (pid,) in _rows(srv.data_dir, "SELECT pid FROM workers")}
    return sorted(running(known) & descendants(srv.process.pid))


def _wait_idle(srv: Server, count: int, timeout: float = 120) -> list[int]:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        pids = _worker_pids(srv)
        busy = _rows(srv.data_dir, "SELECT count(*) FROM jobs WHERE status IN ('queued', 'running')")[0][0]
        if len(pids) == count and busy == 0:
            return pids
        time.sleep(0.2)
    raise AssertionError(f"workers not idle: {_worker_pids(srv)}")


def _terminate(srv: Server, timeout: float = 30.0) -> set[int]:
    """SIGTERM the server (not its group) and wait; returns its processes still running after."""
    tree = descendants(srv.process.pid) | {srv.process.pid}
    srv.process.send_signal(signal.SIGTERM)
    try:
        srv.process.wait(timeout)
    except Exception:  # noqa: BLE001 - reported below
        os.killpg(srv.process.pid, signal.SIGKILL)
        srv.process.wait(10)
        raise AssertionError(f"SIGTERM did not stop the server in {timeout} s:\n{srv.logs()[-3000:]}") from None
    finally:
        srv.log.close()
        srv.process = None
    return wait_gone(tree, 15)


def _assert_invariants(srv: Server, ids: list[str], timeout: float = 240) -> None:
    statuses = settle(_events(srv.data_dir), _status(srv.data_dir), ids, timeout)
    counts = tally(ids, statuses, _events(srv.data_dir))
    assert counts == {"lost": 0, "stuck": 0, "duplicated": 0, "not_succeeded": 0}, (counts, statuses,
                                                                                    srv.logs()[-4000:])


def test_sigkill_server_workers_follow_then_restart_finishes_all(tmp_path, case, slow_case):
    """A SIGKILLed server (only its own pid) takes its workers with it; the next server runs every job once."""
    data = tmp_path / "data"
    first = Server(data, workers=1).start()
    with first.client() as client:
        ids = [submit(client, slow_case, {**SLOW, "seed": 0}).json()["id"],  # running when the server dies
               submit(client, case, {**FAST, "seed": 1}).json()["id"]]  # queued behind it: need not be slow
        wait_for(client, ids[0], statuses=("running",), timeout=60)
    tree = descendants(first.process.pid)
    assert tree, "the server has no child processes"
    os.kill(first.process.pid, signal.SIGKILL)
    first.process.wait(10)
    first.log.close()
    first.process = None
    assert wait_gone(tree, 15) == set(), "worker/validator processes outlived the SIGKILLed server"
    second = Server(data, workers=2).start()
    try:
        with second.client() as client:
            response, took = timed_post(client, case, {**FAST, "seed": 7})
            assert response.status_code == 202 and took < allowed(NEXT_POST_SECONDS), (response.status_code, took)
            ids.append(response.json()["id"])
        _assert_invariants(second, ids)
    finally:
        assert _terminate(second) == set()


@pytest.fixture(scope="module")
def two_workers(tmp_path_factory):
    """A 2-worker server with 30 s leases for the worker-kill and slow-loris tests (each asserts on its own jobs and
    its own part of the log; the server replaces the workers the kill test kills); SIGTERMed after the last of them,
    nothing of it left running."""
    srv = Server(tmp_path_factory.mktemp("two-workers") / "data", workers=2, env={"DSAREG_LEASE_SECONDS": "30"})
    try:
        yield srv.start()
    finally:
        if srv.alive():
            assert _terminate(srv) == set(), "processes left after SIGTERM"


def test_sigkill_idle_worker_then_busy_worker(two_workers, case, slow_case):
    """Killing an idle worker used to leave the shared wake-up lock held: every later POST hung. A killed busy
    worker's job is requeued as soon as the supervisor sees the death, not when its (30 s) lease ends."""
    srv = two_workers
    with srv.client() as client:
        ids = [submit(client, case, FAST).json()["id"]]  # also warms the validator's cache
        _wait_idle(srv, 2)
        idle = _worker_pids(srv)
        time.sleep(1.0)  # both idle inside their wait
        os.kill(idle[0], signal.SIGKILL)
        time.sleep(0.3)
        response, took = timed_post(client, case, {**FAST, "seed": 1})
        assert response.status_code == 202 and took < allowed(NEXT_POST_SECONDS), (response.status_code, took)
        ids.append(response.json()["id"])
        deadline = time.monotonic() + 120
        while len(_worker_pids(srv)) < 2 and time.monotonic() < deadline:  # the replaced idle one warmed up
            time.sleep(0.2)  # (before the slow job starts: waiting while it ran let it finish before the kill)
        busy = submit(client, slow_case, {**SLOW, "seed": 2}).json()["id"]
        ids.append(busy)
        body = wait_for(client, busy, statuses=("running",), timeout=60,
                        predicate=lambda b: (b.get("progress") or {}).get("iteration", 0) > 0)
        (worker_id,) = _rows(srv.data_dir, "SELECT worker_id FROM jobs WHERE id=?", (busy,))[0]
        os.kill(int(worker_id.split("-")[-3]), signal.SIGKILL)
        killed_at = time.time()
        response, took = timed_post(client, case, {**FAST, "seed": 3})
        assert response.status_code == 202 and took < allowed(NEXT_POST_SECONDS), (response.status_code, took)
        ids.append(response.json()["id"])
        _assert_invariants(srv, ids)
        assert body["status"] == "running" and _events(srv.data_dir)(busy).count("claimed") == 2
        at = dict(_rows(srv.data_dir, "SELECT event, max(at) FROM job_events WHERE job_id=? GROUP BY event", (busy,)))
        requeue_s, claim_s = at["lease_expired"] - killed_at, at["claimed"] - killed_at
        print(f"\nbusy worker SIGKILLed: its job requeued after {requeue_s:.2f} s, claimed again after "
              f"{claim_s:.2f} s (lease 30 s)")
        assert requeue_s <= allowed(5.0) and claim_s <= allowed(15.0), (requeue_s, claim_s)
        assert len(_wait_idle(srv, 2)) == 2  # the supervisor replaced both


def test_slow_loris_and_client_disconnect_do_not_hurt(two_workers, case):
    """Uploads that stall or vanish mid-body: other requests are served, nothing is logged as an error."""
    srv = two_workers
    logged_before = len(srv.logs())
    with srv.client() as client:
        ids = [submit(client, case, FAST).json()["id"]]  # warms the validator's cache
        slow = [partial_multipart(srv.port, 10_000_000, MULTIPART_START + b"v 0 0 0\n") for _ in range(8)]
        for sock in slow[:4]:
            sock.sendall(b"v 1 0 0\n")  # trickle
        response, took = timed_post(client, case, {**FAST, "seed": 1})
        assert response.status_code == 202 and took < allowed(NEXT_POST_SECONDS), (response.status_code, took)
        ids.append(response.json()["id"])
        assert client.get("/healthz", timeout=1).status_code == 200
        for sock in slow:  # the clients give up mid-upload
            sock.close()
        time.sleep(1.0)
        response, took = timed_post(client, case, {**FAST, "seed": 2})
        assert response.status_code == 202 and took < allowed(NEXT_POST_SECONDS), (response.status_code, took)
        ids.append(response.json()["id"])
        _assert_invariants(srv, ids)
        metrics = client.get("/metrics").text
    assert 'status="500"' not in metrics, [line for line in metrics.splitlines() if 'status="5' in line]
    assert " ERROR " not in srv.logs()[logged_before:], srv.logs()[-3000:]
