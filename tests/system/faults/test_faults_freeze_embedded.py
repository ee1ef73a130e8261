"""Freezes and full disks in the single-machine topology (API + embedded workers + SQLite), issue 20.

Each test SIGSTOPs or kills a real process (a validator, a worker holding the SQLite write lock)
or fills a real tmpfs under the data directory, and asserts: every request during the fault is
answered within 2 s (success, or 503/507 + Retry-After), then 0 jobs lost, stuck or run twice,
and no process left after the server stops.
"""

from __future__ import annotations

import os
import signal
import sqlite3
import threading
import time

import pytest
from tests.support.faults_kit import (
    ANSWER_SECONDS,
    assert_answered,
    cpu_ticks,
    empty_disk,
    fill_disk,
    frozen,
    record_answer,
    resume,
    settle,
    spawn_children,
    start_ticks,
    stop,
    tally,
    timed,
    tmpfs,
    variant,
    wait_gone,
)
from tests.support.service_testkit import Server, needs_engine, small_cta_case, submit, submit_volume, wait_for
from tests.support.time_bounds import allowed

pytestmark = [needs_engine, pytest.mark.slow]

FAST = {"starts": 1, "max_iterations": 10}
SLOW = {"starts": 8, "max_iterations": 400, "coarse_to_fine": False}  # on slow_case
MiB = 1 << 20


def _rows(db, query, args=()):
    with sqlite3.connect(db, timeout=30) as conn:
        return conn.execute(query, args).fetchall()


class Embedded:
    """A server and the job table it writes (``db``: its SQLite file)."""

    def __init__(self, srv: Server, db):
        self.srv, self.db = srv, db

    def events_of(self, job_id: str) -> list[str]:
        return [r[0] for r in _rows(self.db, "SELECT event FROM job_events WHERE job_id=? ORDER BY seq", (job_id,))]

    def status_of(self, job_id: str) -> str:
        rows = _rows(self.db, "SELECT status FROM jobs WHERE id=?", (job_id,))
        return rows[0][0] if rows else "missing"

    def worker_pids(self) -> set[int]:
        known = {pid for (pid,) in _rows(self.db, "SELECT pid FROM workers")}
        return known & spawn_children(self.srv.process.pid)

    def validator_pids(self) -> list[int]:
        """The validator processes, oldest first (the oldest is the one in use: the other is the spare)."""
        pids = spawn_children(self.srv.process.pid) - self.worker_pids()
        return sorted(pids, key=start_ticks)

    def wait_spare(self, client, timeout: float = 180.0) -> None:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            checks = client.get("/readyz").json().get("checks", {})
            if checks.get("validator_ready") and checks.get("validator_spare_ready", True):
                return
            time.sleep(0.3)
        raise AssertionError("the validators did not warm up")

    def assert_invariants(self, ids: list[str], timeout: float = 300) -> None:
        statuses = settle(self.events_of, self.status_of, ids, timeout)
        counts = tally(ids, statuses, self.events_of)
        assert counts == {"lost": 0, "stuck": 0, "duplicated": 0, "not_succeeded": 0}, (
            counts, statuses, self.srv.logs()[-4000:])

    def stop_and_check(self) -> None:
        tree = spawn_children(self.srv.process.pid) | {self.srv.process.pid}
        self.srv.stop()
        assert wait_gone(tree, 15) == set(), "processes left after the server stopped"


@pytest.fixture(scope="module")
def shared(tmp_path_factory):
    """One server (1 worker, 3 s leases) for the validator and write-lock tests: each asserts on the jobs it submitted,
    and the server replaces the validators and the worker they kill itself. After the last of them: no process left
    once it stops (one start instead of three: each start warms two validators and a worker)."""
    root = tmp_path_factory.mktemp("freeze-embedded")
    db = root / "jobs.sqlite3"
    srv = Server(root / "data", workers=1, env={"DSAREG_DATABASE_URL": f"sqlite:///{db}", "DSAREG_LEASE_SECONDS": "3"})
    try:
        topo = Embedded(srv.start(timeout=240), db)
        yield topo
        topo.stop_and_check()
    finally:
        if srv.alive():
            srv.stop()


@pytest.fixture
def embedded(tmp_path):
    made = []

    def start(workers: int = 1, data_dir=None, env: dict | None = None) -> Embedded:
        data = data_dir or tmp_path / "data"
        db = tmp_path / "jobs.sqlite3"
        srv = Server(data, workers=workers, env={"DSAREG_DATABASE_URL": f"sqlite:///{db}", **(env or {})})
        made.append(srv)
        return Embedded(srv.start(timeout=240), db)

    yield start
    for srv in made:
        if srv.alive():
            srv.stop()


def test_disk_full_in_the_data_dir(embedded, tmp_path, case, slow_case):
    """A small real tmpfs as the data dir: below DSAREG_MIN_FREE_BYTES a POST is 507 + Retry-After before
    anything is written; a job whose outputs hit ENOSPC is released (no attempt used), and finishes once
    there is room. Nothing at ERROR, no traceback."""
    with tmpfs(tmp_path / "data", 96 * MiB) as disk:  # the data dir itself (the server log stays outside)
        topo = embedded(data_dir=disk, env={"DSAREG_MIN_FREE_BYTES": str(24 * MiB)})
        with topo.srv.client() as client:
            ids = [submit(client, case, FAST).json()["id"]]
            wait_for(client, ids[0], timeout=120)
            fill_disk(disk, leave_bytes=16 * MiB)  # below the floor, with room left
            blobs_before = sorted(p.name for p in (disk / "blobs").rglob("*"))
            response, took = timed(lambda: submit(client, variant(case, 1), FAST))
            assert_answered(response, took, ok=(), refusals=(507,), what="POST below the floor")
            assert sorted(p.name for p in (disk / "blobs").rglob("*")) == blobs_before
            assert list((disk / "tmp").iterdir()) == []
            empty_disk(disk)
            job_id, _ = _running_worker(topo, client, slow_case, 2)
            ids.append(job_id)
            fill_disk(disk)  # to ENOSPC while the registration runs: its outputs cannot be written
            deadline = time.monotonic() + 240
            while "released:disk_full" not in topo.events_of(job_id) and time.monotonic() < deadline:
                response, took = timed(lambda: client.get(f"/v1/registrations/{job_id}"))
                assert_answered(response, took, ok=(200,), what="GET while the disk is full")
                time.sleep(0.5)
            assert "released:disk_full" in topo.events_of(job_id), (topo.events_of(job_id), topo.srv.logs()[-3000:])
            response, took = timed(lambda: submit(client, variant(case, 3), FAST))
            assert_answered(response, took, ok=(), refusals=(507,), what="POST on a full disk")
            time.sleep(2.0)  # below the floor the worker claims nothing
            assert topo.status_of(job_id) == "queued"
            empty_disk(disk)
            topo.assert_invariants(ids)
            assert _rows(topo.db, "SELECT attempts FROM jobs WHERE id=?", (job_id,))[0][0] == 1
        logs = topo.srv.logs()
        assert " ERROR " not in logs and "Traceback" not in logs, logs[-4000:]
        assert "no space left on the data disk" in logs
        topo.stop_and_check()


def test_frozen_validator_is_replaced_and_the_request_answered(shared, case):
    """SIGSTOP of the validator in use: the POST is answered by the warm spare within 2 s (was 20-60 s)."""
    topo = shared
    with topo.srv.client() as client:
        ids = [submit(client, case, FAST).json()["id"]]
        topo.wait_spare(client)
        victim = topo.validator_pids()[0]
        with frozen([victim]):
            response, took = timed(lambda: submit(client, variant(case, 1), FAST))
            assert_answered(response, took, ok=(202,), what="POST with a frozen validator")
            ids.append(response.json()["id"])
        assert victim not in topo.validator_pids()  # killed, not left stopped
        topo.wait_spare(client)
        response, took = timed(lambda: submit(client, variant(case, 2), FAST))
        assert_answered(response, took, ok=(202,), what="the next POST")
        ids.append(response.json()["id"])
        topo.assert_invariants(ids)


def _post_killing_the_parser(client, topo: Embedded, case, n: int) -> tuple[object, float, bool]:
    """POST a new input and SIGKILL the validator as soon as it starts parsing it; (response, s, killed)."""
    victim = topo.validator_pids()[0]
    before = cpu_ticks(victim)
    box: dict = {}
    thread = threading.Thread(target=lambda: box.update(answer=timed(lambda: submit(client, variant(case, n), FAST))))
    thread.start()
    killed = False
    while thread.is_alive() and not killed:
        if cpu_ticks(victim) > before:  # it got the request and is parsing
            os.kill(victim, signal.SIGKILL)
            killed = True
        time.sleep(0.002)
    thread.join(120)
    response, took = box["answer"]
    return response, took, killed


def test_validator_killed_mid_parse_is_retried_on_a_fresh_one(shared, case):
    """SIGKILL mid-parse: the upload is parsed again by the spare (202), never a 422 without a field."""
    topo = shared
    logged_before = len(topo.srv.logs())
    with topo.srv.client() as client:
        ids = [submit(client, case, FAST).json()["id"]]
        kills = 0
        for n in range(10, 16):
            topo.wait_spare(client)
            response, took, killed = _post_killing_the_parser(client, topo, case, n)
            record_answer("POST, validator SIGKILLed mid-parse" if killed else "POST, kill too late", response.status_code,
                          took)
            assert response.status_code == 202, (response.status_code, response.text[:300])
            assert took < allowed(2 * ANSWER_SECONDS), took  # two parses of the input
            ids.append(response.json()["id"])
            kills += killed
            if kills >= 2:
                break
        assert kills >= 1, "the parse always finished before the kill landed"
        response, took = timed(lambda: submit(client, variant(case, 20), FAST))
        assert_answered(response, took, ok=(202,), what="the next POST")
        ids.append(response.json()["id"])
        topo.assert_invariants(ids)
    assert "validator replaced (dead)" in topo.srv.logs()[logged_before:]


def _locked(db) -> bool:
    conn = sqlite3.connect(db, timeout=0)
    try:
        conn.execute("BEGIN IMMEDIATE")
        conn.rollback()
        return False
    except sqlite3.OperationalError:
        return True
    finally:
        conn.close()


def _freeze_holding_the_write_lock(pid: int, db, timeout: float = 120.0) -> None:
    """SIGSTOP ``pid`` at a moment it holds the SQLite write lock (a heartbeat or progress write):
    stop, look, resume, until the lock is found held — and still held 0.1 s later (not the API's)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        stop([pid])
        if _locked(db):
            time.sleep(0.1)
            if _locked(db):
                return
        resume([pid])
        time.sleep(0.001)
    raise AssertionError("never caught the worker inside a write transaction")


def _running_worker(topo: Embedded, client, slow_case, seed: int) -> tuple[str, int]:
    job_id = submit(client, slow_case, {**SLOW, "seed": seed}).json()["id"]
    wait_for(client, job_id, statuses=("running",), timeout=120,
             predicate=lambda b: (b.get("progress") or {}).get("iteration", 0) > 0)
    (worker_id,) = _rows(topo.db, "SELECT worker_id FROM jobs WHERE id=?", (job_id,))[0]
    return job_id, int(worker_id.split("-")[-3])


def _requests_during_lock(client, case, seed: int) -> None:
    """POST, /readyz and a GET while the write lock is held: each answered within 2 s."""
    response, took = timed(lambda: submit(client, case, {**FAST, "seed": seed}))
    assert_answered(response, took, ok=(202,), what="POST while the write lock is held")
    assert response.status_code == 503, response.status_code
    ready, took = timed(lambda: client.get("/readyz"))
    assert_answered(ready, took, ok=(), what="/readyz while the write lock is held", problem=False)
    listed, took = timed(lambda: client.get("/v1/registrations"))
    assert_answered(listed, took, ok=(200,), what="list while the write lock is held")



def test_worker_frozen_holding_the_sqlite_write_lock(shared, case, slow_case):
    """POST and /readyz answer 503 + Retry-After within 2 s (was 30 s); the job finishes once the
    worker resumes, and once more after a worker frozen the same way is SIGKILLed."""
    topo = shared  # 3 s leases
    with topo.srv.client() as client:
        ids = [submit(client, case, FAST).json()["id"]]
        wait_for(client, ids[0], timeout=120)
        resumed, pid = _running_worker(topo, client, slow_case, 1)
        ids.append(resumed)
        _freeze_holding_the_write_lock(pid, topo.db)
        try:
            _requests_during_lock(client, case, 2)
        finally:
            resume([pid])
        killed, pid = _running_worker(topo, client, slow_case, 3)
        ids.append(killed)
        _freeze_holding_the_write_lock(pid, topo.db)
        _requests_during_lock(client, case, 4)
        os.kill(pid, signal.SIGKILL)  # the lock goes with it; the lease expires; attempt 2
        response, took = timed(lambda: submit(client, case, {**FAST, "seed": 5}))
        assert_answered(response, took, ok=(202,), what="POST after the kill")
        ids.append(response.json()["id"])
        topo.assert_invariants(ids)
    assert topo.events_of(resumed).count("claimed") == 1
    assert topo.events_of(killed).count("claimed") == 2


@pytest.fixture(scope="module")
def cta_series():
    return small_cta_case(voxel_mm=0.8)


def _frozen_while_reading(topo: Embedded, client, series, seed: int, tries: int = 4) -> tuple[str, int, list[str]]:
    """A volume job's worker SIGSTOPped as soon as it claimed the job, before its first progress (it is reading the
    series' stored files, which it reads when used: ``engine.FileParts``). ``(job, pid, ids of every try)``."""
    ids = []
    for attempt in range(tries):
        response = submit_volume(client, series, {**FAST, "seed": seed * 10 + attempt})
        assert response.status_code == 202, response.text
        job_id = response.json()["id"]
        ids.append(job_id)
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline:
            rows = _rows(topo.db, "SELECT worker_id, progress FROM jobs WHERE id=?", (job_id,))
            if rows and rows[0][0]:
                break
            time.sleep(0.002)
        pid = int(rows[0][0].split("-")[-3])
        stop([pid])
        (progress,) = _rows(topo.db, "SELECT progress FROM jobs WHERE id=?", (job_id,))[0]
        if not progress:  # frozen inside the read
            return job_id, pid, ids
        resume([pid])
        wait_for(client, job_id, timeout=120)
    raise AssertionError(f"the worker was never frozen before its first progress ({tries} tries)")


def test_worker_frozen_or_killed_while_reading_a_volume_series(shared, case, cta_series):
    """A worker reads a volume's stored series when it uses each file: frozen in that read, requests are answered
    within 2 s and the job finishes once it resumes (or on a fresh worker once its lease ends); killed in it, the
    job is claimed again and finishes; nothing lost, stuck or run twice, and the results say how the volume was read."""
    topo = shared  # 3 s leases, 1 worker
    with topo.srv.client() as client:
        resumed, pid, ids = _frozen_while_reading(topo, client, cta_series, 1)
        try:
            response, took = timed(lambda: submit(client, case, {**FAST, "seed": 7}))
            assert_answered(response, took, ok=(202,), what="POST while a worker is frozen in a volume's read")
            ids.append(response.json()["id"])
            time.sleep(allowed(4.0))  # past the lease
        finally:
            resume([pid])
        killed, pid, more = _frozen_while_reading(topo, client, cta_series, 2)
        ids += more
        os.kill(pid, signal.SIGKILL)
        response, took = timed(lambda: submit(client, case, {**FAST, "seed": 8}))
        assert_answered(response, took, ok=(202,), what="POST after the reading worker was killed")
        ids.append(response.json()["id"])
        topo.assert_invariants(ids)
        for job_id in (resumed, killed):
            result = client.get(f"/v1/registrations/{job_id}/result").json()
            assert result["volume"]["kind"] == "cta" and result["volume"]["voxels_kept"] > 0, result.get("volume")
    assert topo.events_of(killed).count("claimed") == 2
