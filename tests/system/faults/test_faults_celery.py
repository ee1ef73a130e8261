"""Faults injected into the scale-out topology: API + Celery workers + Redis + PostgreSQL, all real
processes on loopback. Same invariants as the embedded suite: 0 lost, 0 stuck, 0 run twice to
completion, the next POST answered within 1 s, no orphan processes."""

from __future__ import annotations

import os
import signal
import time

import pytest
from tests.support.faults_kit import NEXT_POST_SECONDS, descendants, settle, tally, timed_post, wait_gone
from tests.support.scaleout_kit import CeleryTopology, pid_of_worker_id
from tests.support.service_testkit import needs_engine, submit, wait_for
from tests.support.time_bounds import allowed

pytestmark = [needs_engine, pytest.mark.slow]

FAST = {"starts": 1, "max_iterations": 10}
SLOW = {"starts": 8, "max_iterations": 400, "coarse_to_fine": False}  # on slow_case


class Topology(CeleryTopology):
    """The scale-out topology with the fault suite's invariants."""

    def assert_invariants(self, ids: list[str], timeout: float = 180) -> None:
        statuses = settle(self.events_of, self.status_of, ids, timeout)
        counts = tally(ids, statuses, self.events_of)
        assert counts == {"lost": 0, "stuck": 0, "duplicated": 0, "not_succeeded": 0}, (counts, statuses, self.logs())


@pytest.fixture(scope="module")
def topology(tmp_path_factory, redis_server, postgres_server, case):
    topo = Topology(tmp_path_factory.mktemp("faults-celery"), redis_server, postgres_server)
    topo.api.start()
    topo.add_worker()
    topo.add_worker()
    topo.wait_workers(2)
    with topo.api.client() as client:  # the validator has parsed the case once
        first = submit(client, case, FAST).json()["id"]
        wait_for(client, first, timeout=120)
    try:
        yield topo
    finally:
        topo.stop_workers()
        topo.api.stop()
        topo.store.dispose()


def _running_job_pid(topo: Topology, job_id: str, client) -> int:
    wait_for(client, job_id, statuses=("running",), timeout=90,
             predicate=lambda b: (b.get("progress") or {}).get("iteration", 0) > 0)
    return pid_of_worker_id(topo.store.get(job_id).worker_id)


def test_celery_tasks_honour_the_thread_budget(topology):
    """numba's thread count is per thread: it must be set on the pool thread that runs the task."""
    logs = "".join(w.logs() for w in topology.workers)
    assert "runs on 1 torch / 1 numba threads" in logs, logs[-3000:]
    assert "numba threads" in logs and "/ 2 numba threads" not in logs


def test_celery_kill_busy_worker(topology, case, slow_case):
    with topology.api.client() as client:
        ids = [submit(client, slow_case, {**SLOW, "seed": 11}).json()["id"]]
        victim_pid = _running_job_pid(topology, ids[0], client)
        victim = next(w for w in topology.workers if w.pid == victim_pid)
        victim.kill()  # SIGKILL: the message stays unacked, the lease expires
        response, took = timed_post(client, case, {**FAST, "seed": 12})
        assert response.status_code == 202 and took < allowed(NEXT_POST_SECONDS), (response.status_code, took)
        ids.append(response.json()["id"])
        topology.workers.remove(victim)
        topology.add_worker()
        topology.assert_invariants(ids)
    assert topology.store.get(ids[0]).attempts == 2


def test_celery_postgres_outage(topology, case, slow_case):
    """Database down while a job runs: the API answers 503 + Retry-After (not 500); the job's
    finished result is saved once the database is back (attempt 1, no 'worker stopped responding')."""
    with topology.api.client() as client:
        job_id = submit(client, slow_case, {**SLOW, "seed": 21}).json()["id"]
        pid = _running_job_pid(topology, job_id, client)
        worker = next(w for w in topology.workers if w.pid == pid)
        topology.postgres.pause()
        paused_at = time.monotonic()  # the job's last lease renewal was before this
        try:
            response, took = timed_post(client, case, {**FAST, "seed": 22})
            assert response.status_code == 503 and took < allowed(NEXT_POST_SECONDS), (response.status_code, took)
            assert response.headers["content-type"].startswith("application/problem+json")
            assert int(response.headers["retry-after"]) > 0
            status = client.get(f"/v1/registrations/{job_id}")
            assert status.status_code == 503 and "retry-after" in status.headers
            finished = (f"job {job_id}: storing artifacts failed", f"job {job_id}: saving 'succeeded' failed")
            deadline = time.monotonic() + 90  # the registration ends while the database is still down
            while not any(m in worker.logs() for m in finished) and time.monotonic() < deadline:
                time.sleep(0.5)
            assert any(m in worker.logs() for m in finished), worker.logs()[-3000:]
            lease_s = float(topology.env["DSAREG_LEASE_SECONDS"])  # the database stays down well past the job's lease
            time.sleep(max(0.0, paused_at + 2 * lease_s - time.monotonic()))  # (was 12 s after the job's end)
        finally:
            topology.postgres.resume()
        topology.assert_invariants([job_id])
        assert topology.store.get(job_id).attempts == 1, topology.events_of(job_id)
        response, took = timed_post(client, case, {**FAST, "seed": 23})
        assert response.status_code == 202 and took < allowed(NEXT_POST_SECONDS), (response.status_code, took)
        topology.assert_invariants([response.json()["id"]])


def test_celery_redis_restart(topology, case):
    if not hasattr(topology.redis, "kill"):
        pytest.skip("Redis given by URL: cannot restart it")
    with topology.api.client() as client:
        ids = [submit(client, case, {**FAST, "seed": 30 + n}).json()["id"] for n in range(4)]
        topology.redis.kill()  # no persistence: queued messages are gone
        topology.redis.start()
        response, took = timed_post(client, case, {**FAST, "seed": 40})
        assert response.status_code == 202 and took < allowed(NEXT_POST_SECONDS + 2.0), (response.status_code, took)
        ids.append(response.json()["id"])
        topology.assert_invariants(ids)


def test_celery_sigkill_api_then_restart(topology, case):
    """The API (no embedded workers) SIGKILLed: its validator goes with it; a new API serves the same jobs."""
    api = topology.api
    with api.client() as client:
        ids = [submit(client, case, {**FAST, "seed": 50 + n}).json()["id"] for n in range(2)]
    tree = descendants(api.process.pid)
    os.kill(api.process.pid, signal.SIGKILL)
    api.process.wait(10)
    api.log.close()
    api.process = None
    assert wait_gone(tree, 15) == set(), "the validator outlived the SIGKILLed API"
    api.start()
    topology.wait_workers(2)  # /readyz: store, workers and the warmed-up validator
    with api.client() as client:
        response, took = timed_post(client, case, {**FAST, "seed": 60})
        assert response.status_code == 202 and took < allowed(NEXT_POST_SECONDS), (response.status_code, took)
        ids.append(response.json()["id"])
    topology.assert_invariants(ids)
