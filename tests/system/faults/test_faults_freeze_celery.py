"""Freezes and full disks in the scale-out topology (API + Celery workers + Redis + PostgreSQL), issue 20.

SIGSTOP of the whole PostgreSQL cluster or of Redis, and a real tmpfs under the API's and the
workers' data directories filled up. Every request during the fault is answered within 2 s
(success, or 503/507 + Retry-After); afterwards 0 jobs lost, stuck or run twice.
"""

from __future__ import annotations

import time
from pathlib import Path

import pytest
from tests.support.faults_kit import (
    assert_answered,
    descendants,
    empty_disk,
    fill_disk,
    frozen,
    running,
    settle,
    tally,
    timed,
    tmpfs,
    variant,
    wait_gone,
)
from tests.support.scaleout_kit import CeleryTopology
from tests.support.service_testkit import needs_engine, submit, wait_for

pytestmark = [needs_engine, pytest.mark.slow]

FAST = {"starts": 1, "max_iterations": 10}
SLOW = {"starts": 8, "max_iterations": 400, "coarse_to_fine": False}  # on slow_case
MiB = 1 << 20
FLOOR = 24 * MiB


class Topology(CeleryTopology):
    def assert_invariants(self, ids: list[str], timeout: float = 300) -> None:
        statuses = settle(self.events_of, self.status_of, ids, timeout)
        counts = tally(ids, statuses, self.events_of)
        assert counts == {"lost": 0, "stuck": 0, "duplicated": 0, "not_succeeded": 0}, (counts, statuses, self.logs())

    def postgres_pids(self) -> set[int]:
        postmaster = int((Path(self.postgres.data) / "postmaster.pid").read_text().split()[0])
        return running({postmaster} | descendants(postmaster))


@pytest.fixture(scope="module")
def root(tmp_path_factory):
    return tmp_path_factory.mktemp("faults-freeze-celery")


@pytest.fixture(scope="module")
def disks(root):
    """The API's and the worker's data dirs, each a small tmpfs (their logs stay outside, in ``root``)."""
    with tmpfs(root / "api", 128 * MiB) as api, tmpfs(root / "w1", 128 * MiB) as worker:
        yield [api, worker]


@pytest.fixture(scope="module")
def topology(root, disks, redis_server, postgres_server, case):
    topo = Topology(root, redis_server, postgres_server)
    topo.env["DSAREG_MIN_FREE_BYTES"] = str(FLOOR)
    topo.api.env = topo.env
    topo.api.start(timeout=240)
    topo.add_worker()
    topo.wait_workers(1, timeout=240)
    with topo.api.client() as client:
        wait_for(client, submit(client, case, FAST).json()["id"], timeout=240)
    tree = descendants(topo.api.process.pid) | {topo.api.process.pid}
    try:
        yield topo
    finally:
        topo.stop_workers()
        topo.api.stop()
        topo.store.dispose()
        assert wait_gone(tree, 15) == set(), "processes left after the API stopped"


def _running(topo: Topology, client, slow_case, seed: int) -> str:
    job_id = submit(client, slow_case, {**SLOW, "seed": seed}).json()["id"]
    wait_for(client, job_id, statuses=("running",), timeout=180,
             predicate=lambda b: (b.get("progress") or {}).get("iteration", 0) > 0)
    return job_id


def test_frozen_postgres_gives_503_within_2s_and_recovers(topology, case, slow_case):
    """SIGSTOP of every PostgreSQL process: POST, GET, list and /readyz 503 + Retry-After in < 2 s
    (was ≈ 39.5 s each); after SIGCONT everything works and the running job finishes once."""
    with topology.api.client() as client:
        ids = [_running(topology, client, slow_case, 1)]
        with frozen(topology.postgres_pids()):
            for what, call in (("POST", lambda: submit(client, case, {**FAST, "seed": 2})),
                               ("GET", lambda: client.get(f"/v1/registrations/{ids[0]}")),
                               ("list", lambda: client.get("/v1/registrations")),
                               ("readyz", lambda: client.get("/readyz")),
                               ("POST again", lambda: submit(client, case, {**FAST, "seed": 3}))):
                response, took = timed(call)
                assert_answered(response, took, ok=(), refusals=(503,), what=f"{what} on a frozen PostgreSQL",
                                problem=what != "readyz")
        response, took = timed(lambda: submit(client, case, {**FAST, "seed": 4}))
        assert_answered(response, took, ok=(202,), what="POST after SIGCONT")
        ids.append(response.json()["id"])
        for what, call in (("GET", lambda: client.get(f"/v1/registrations/{ids[0]}")),
                           ("list", lambda: client.get("/v1/registrations"))):
            response, took = timed(call)
            assert_answered(response, took, ok=(200,), refusals=(), what=f"{what} after SIGCONT")
        topology.assert_invariants(ids)


def test_frozen_redis_publish_is_bounded_and_the_job_redispatched(topology, case):
    """SIGSTOP of Redis: POST answers 202 in < 2 s (was 39.5 s), the job stays queued in the table and
    is re-sent by the sweeper after SIGCONT; 0 lost."""
    with topology.api.client() as client:
        ids = []
        with frozen([topology.redis.process.pid]):
            for n in range(2):
                response, took = timed(lambda n=n: submit(client, case, {**FAST, "seed": 10 + n}))
                assert_answered(response, took, ok=(202,), refusals=(), what="POST on a frozen Redis")
                ids.append(response.json()["id"])
            response, took = timed(lambda: client.get(f"/v1/registrations/{ids[0]}"))
            assert_answered(response, took, ok=(200,), refusals=(), what="GET on a frozen Redis")
            assert response.json()["status"] == "queued"
        topology.assert_invariants(ids)
    assert "broker unreachable" in topology.api.logs()


def _fill(disks, leave_bytes: int = 0) -> None:
    for disk in disks:
        fill_disk(disk, leave_bytes)


def _empty(disks) -> None:
    for disk in disks:
        empty_disk(disk)


def test_disk_full_in_the_data_dirs(topology, disks, case, slow_case):
    """Below the floor a POST is 507 + Retry-After before writing; a job whose outputs hit ENOSPC on the
    worker is released (no attempt used) and redispatched once there is room. Nothing at ERROR."""
    with topology.api.client() as client:
        _fill(disks, leave_bytes=FLOOR // 2)
        try:
            response, took = timed(lambda: submit(client, variant(case, 1), FAST))
            assert_answered(response, took, ok=(), refusals=(507,), what="POST below the floor")
        finally:
            _empty(disks)
        job_id = _running(topology, client, slow_case, 20)
        _fill(disks)
        try:
            deadline = time.monotonic() + 240
            while "released:disk_full" not in topology.events_of(job_id) and time.monotonic() < deadline:
                response, took = timed(lambda: client.get(f"/v1/registrations/{job_id}"))
                assert_answered(response, took, ok=(200,), what="GET while the disk is full")
                time.sleep(0.5)
            assert "released:disk_full" in topology.events_of(job_id), (topology.events_of(job_id), topology.logs())
            response, took = timed(lambda: submit(client, variant(case, 2), FAST))
            assert_answered(response, took, ok=(), refusals=(507,), what="POST on a full disk")
        finally:
            _empty(disks)
        topology.assert_invariants([job_id])
        assert topology.store.get(job_id).attempts == 1, topology.events_of(job_id)
    logs = topology.logs()
    assert "no space left on the data disk" in logs
    assert " ERROR " not in topology.api.logs() and "Traceback" not in topology.api.logs(), topology.api.logs()[-3000:]
