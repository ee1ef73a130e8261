"""Scale-out on loopback with real services: Redis + PostgreSQL + the API + Celery worker processes.

The API and each worker have their own data directory (no shared filesystem): inputs and
artifacts travel through the database blob table.
"""

from __future__ import annotations

import signal
import time

import numpy as np
import pytest
from tests.support.scaleout_kit import CeleryTopology, CeleryWorker, RedisServer, pid_of_worker_id
from tests.support.service_testkit import (Server, make_example_case, needs_engine, small_cta_case, submit,
                                          submit_volume, wait_for)
from tests.support.time_bounds import allowed

pytestmark = [needs_engine, pytest.mark.slow]

SIZE = 64
# ~1.3 s per job on one quiet core: a job must still be running when the test looks for one to kill
# (10 iterations at 64 px end in ~0.1 s once the workers are warmed up, between two progress writes)
OPTIONS = {"starts": 4, "max_iterations": 300, "coarse_to_fine": False, "working_size_px": 192}
# ~15 s on one core (the engine's stop rules end small cases early): long enough to act on it mid-run
LONG_OPTIONS = {"starts": 64, "max_iterations": 5000, "seed": 1, "start_spread_deg": 30, "coarse_to_fine": False,
                "working_size_px": 256}
# the same search on 16 starts (~2.4 CPU-s, ~10.6 for LONG): runs through several of the event stream's 0.5 s polls
EVENTS_OPTIONS = {**LONG_OPTIONS, "starts": 16}


@pytest.fixture(scope="module")
def case(tmp_path_factory):
    return make_example_case(tmp_path_factory.mktemp("case"), SIZE)


@pytest.fixture(scope="module")
def reference(tmp_path_factory, case):
    """The embedded executor's result for the same inputs and seed (SQLite, file blobs)."""
    server = Server(tmp_path_factory.mktemp("embedded") / "data", workers=1,
                    env={"DSAREG_THREADS_PER_WORKER": "1", "DSAREG_LEASE_SECONDS": "15"}).start()
    try:
        with server.client() as client:
            response = submit(client, case, OPTIONS)
            assert response.status_code == 202, response.text
            body = wait_for(client, response.json()["id"], timeout=120)
            assert body["status"] == "succeeded", (body, server.logs()[-4000:])
            return body["result"]
    finally:
        server.stop()


@pytest.fixture(scope="module")
def topology(tmp_path_factory, redis_server, postgres_server):
    topo = CeleryTopology(tmp_path_factory.mktemp("topology"), redis_server, postgres_server)
    topo.api.start()
    try:
        yield topo
    finally:
        topo.stop_workers()
        topo.api.stop()
        topo.store.dispose()


def _submit_many(client, case, n, options=OPTIONS) -> list[str]:
    ids = []
    for _ in range(n):
        response = submit(client, case, options)
        assert response.status_code == 202, response.text
        ids.append(response.json()["id"])
    return ids


def _wait_all(client, ids, timeout) -> dict[str, dict]:
    deadline = time.monotonic() + timeout
    return {job_id: wait_for(client, job_id, timeout=max(1.0, deadline - time.monotonic())) for job_id in ids}


def _two_idle_workers(topology: CeleryTopology) -> tuple[CeleryWorker, CeleryWorker]:
    """Exactly two live, idle workers: those left alive by the tests before (their jobs are over; each start costs
    a worker's warm start) and new ones for the rest; dead ones are closed, live ones beyond two stopped."""
    alive = [worker for worker in topology.workers if worker.alive()]
    for worker in topology.workers:
        if worker not in alive[:2]:
            worker.stop()
    topology.workers = alive[:2]
    while len(topology.workers) < 2:
        topology.add_worker()
    topology.wait_workers(2)
    return topology.workers[0], topology.workers[1]


def test_kill_a_worker_mid_job_every_job_once(topology, case, reference):
    """6 jobs, 2 workers, SIGKILL one worker while it runs a job: all succeed exactly once."""
    victim_a, victim_b = topology.add_worker(), topology.add_worker()
    topology.wait_workers(2)
    with topology.api.client() as client:
        ids = _submit_many(client, case, 6)
        killed_job, victim = None, None
        deadline = time.monotonic() + 60
        while killed_job is None and time.monotonic() < deadline:
            for job_id in ids:
                job = topology.store.get(job_id)
                if job.status == "running" and job.progress and job.worker_id:
                    pid = pid_of_worker_id(job.worker_id)
                    victim = next((w for w in (victim_a, victim_b) if w.pid == pid), None)
                    if victim is not None:
                        victim.kill()  # SIGKILL: no cleanup, the message stays unacked, the lease just expires
                        killed_job = job_id
                        break
            time.sleep(0.05)
        assert killed_job is not None, "no job seen running mid-job"

        finals = _wait_all(client, ids, timeout=150)
        for job_id, body in finals.items():
            assert body["status"] == "succeeded", (body, topology.logs())
            events = [e["event"] for e in topology.store.events(job_id)]
            assert events.count("succeeded") == 1, events
            np.testing.assert_allclose(np.asarray(body["result"]["mesh_to_world"]),
                                       np.asarray(reference["mesh_to_world"]), rtol=0, atol=1e-5)
            # artifacts written by a worker (own data dir) are served by the API from the blob table
            overlay = client.get(f"/v1/registrations/{job_id}/overlays/ap.png")
            assert overlay.status_code == 200 and overlay.content[:8] == b"\x89PNG\r\n\x1a\n"
        killed = topology.store.get(killed_job)
        events = [e["event"] for e in topology.store.events(killed_job)]
        assert "lease_expired" in events and events.count("claimed") == 2, events
        assert killed.attempts == 2

        # the dead worker's unacked message comes back after the visibility timeout; the
        # surviving worker must drop it (the job is finished) instead of running it again
        survivor = victim_b if victim is victim_a else victim_a
        deadline = time.monotonic() + 45
        while time.monotonic() < deadline and f"job {killed_job}: not queued any more" not in survivor.logs():
            time.sleep(0.5)
        assert f"job {killed_job}: not queued any more" in survivor.logs(), survivor.logs()[-3000:]
        assert [e["event"] for e in topology.store.events(killed_job)].count("succeeded") == 1


def test_redis_restart_with_queued_jobs_loses_none(topology, case):
    if not isinstance(topology.redis, RedisServer):
        pytest.skip("Redis given by DSAREG_TEST_REDIS_URL: the test cannot restart it")
    topology.stop_workers()
    with topology.api.client() as client:
        ids = _submit_many(client, case, 3)
        # the broker holds the 3 messages; restart it without persistence: they are gone
        topology.redis.kill()
        topology.redis.start()
        topology.add_worker()
        finals = _wait_all(client, ids, timeout=120)
    for body in finals.values():
        assert body["status"] == "succeeded", (body, topology.logs())
    assert "re-dispatched" in topology.api.logs()


def test_cancel_running_job_on_celery_worker(topology, case):
    if not topology.workers:
        topology.add_worker()
    topology.wait_workers(1)
    with topology.api.client() as client:
        job_id = _submit_many(client, case, 1, LONG_OPTIONS)[0]
        wait_for(client, job_id, statuses=("running",), timeout=60,
                 predicate=lambda b: (b.get("progress") or {}).get("iteration", 0) > 0)
        asked = time.monotonic()
        response = client.post(f"/v1/registrations/{job_id}/cancel")
        assert response.status_code == 202, response.text
        body = wait_for(client, job_id, timeout=30)
        took = time.monotonic() - asked
    assert body["status"] == "canceled", body
    assert took < allowed(10.0), took
    events = topology.store.events(job_id)
    assert [e["event"] for e in events][-2:] == ["cancel_requested", "canceled"]
    assert events[-1]["worker_id"], "the worker itself stopped the job (not the sweeper)"
    # the worker is free again for the next job
    with topology.api.client() as client:
        again = wait_for(client, _submit_many(client, case, 1)[0], timeout=60)
    assert again["status"] == "succeeded"


def test_sigterm_releases_running_job_to_another_worker(topology, case):
    """Warm shutdown (docker stop): the running job goes back to the queue and another worker takes it."""
    first, second = _two_idle_workers(topology)
    with topology.api.client() as client:
        job_id = _submit_many(client, case, 1, LONG_OPTIONS)[0]
        wait_for(client, job_id, statuses=("running",), timeout=60,
                 predicate=lambda b: (b.get("progress") or {}).get("iteration", 0) > 0)
        owner = topology.store.get(job_id).worker_id
        stopping = first if first.pid == pid_of_worker_id(owner) else second
        other = second if stopping is first else first
        stopping.process.send_signal(signal.SIGTERM)
        stopping.process.wait(30)
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline:
            job = topology.store.get(job_id)
            if job.status == "running" and job.worker_id and pid_of_worker_id(job.worker_id) == other.pid:
                break
            time.sleep(0.1)
        events = [e["event"] for e in topology.store.events(job_id)]
        assert events[:3] == ["queued", "claimed", "released"], (events, stopping.logs()[-2000:])
        assert pid_of_worker_id(topology.store.get(job_id).worker_id) == other.pid, events
        assert topology.store.get(job_id).attempts == 1  # a release does not use up an attempt
        client.post(f"/v1/registrations/{job_id}/cancel")
        assert wait_for(client, job_id, timeout=30)["status"] == "canceled"


def test_progress_events_from_a_celery_worker(topology, case):
    """``GET …/events`` reads the store the Celery workers write progress to: progress, then one end event."""
    from service.cli.client import parse_event_stream

    if not topology.workers:
        topology.add_worker()
    topology.wait_workers(1)
    with topology.api.client() as client:
        job_id = _submit_many(client, case, 1, EVENTS_OPTIONS)[0]  # runs long enough for several progress writes
        with client.stream("GET", f"/v1/registrations/{job_id}/events", timeout=120) as response:
            assert response.status_code == 200 and response.headers["content-type"].startswith("text/event-stream")
            frames = list(parse_event_stream(response.iter_lines()))
    assert [f["event"] for f in frames][-1] == "end" and all(f["event"] == "progress" for f in frames[:-1])
    assert any(f["data"]["status"] == "running" and (f["data"]["progress"] or {}).get("iteration", 0) > 0
               for f in frames[:-1]), frames
    assert frames[-1]["data"]["status"] == "succeeded" and frames[-1]["data"]["verdict"] in ("ok", "check", "failed")


def test_a_volume_series_is_read_from_the_database_blobs(topology):
    """A CTA series through the blob table (no shared filesystem): the API's check reads it and keeps its model in
    the database (``volume_models``), the Celery worker (another data folder) takes that model instead of reading
    the series again, and registers it; the series' blobs are read by headers and whole files
    (``BlobStore.read_head``, ``FileParts``) wherever it is read."""
    cta = small_cta_case()
    if not topology.workers:
        topology.add_worker()
    topology.wait_workers(1)
    options = {"initialization": "given", "initial_mesh_to_world": np.eye(4).tolist(), "starts": 1,
               "ground_truth_mesh_to_world": cta.mesh_to_world.tolist()}
    with topology.api.client() as client:
        response = submit_volume(client, cta, options)
        assert response.status_code == 202, response.text
        job = wait_for(client, response.json()["id"], timeout=300)
    assert job["status"] == "succeeded", (job, topology.logs())
    assert job["result"]["volume"]["kind"] == "cta" and job["result"]["volume"]["faces"] > 500
    assert job["result"]["metrics"]["ground_truth"]["add_mm"] < 0.6
    with topology.store.engine.connect() as conn:
        assert conn.exec_driver_sql("SELECT count(*) FROM volume_models").scalar() >= 1
    worker_logs = "\n".join(worker.logs() for worker in topology.workers)
    assert f"job {job['id']}: the volume's model from the shared store" in worker_logs, topology.logs()


def test_a_worker_frozen_then_killed_on_a_volume_job_loses_nothing(topology):
    """A Celery worker running a CTA series' job (the model pulled from the shared store, the series read from the
    blob table) is SIGSTOPped, then SIGKILLed past its lease: the API answers meanwhile, the other worker takes the
    job and finishes it once, the shared store holds the model once, no temporary model file is left, and the
    killed process is gone."""
    import os

    import sqlalchemy as sa

    from service.engine_adapter import engine, volume_model_key

    cta = small_cta_case(0.9)
    first, second = _two_idle_workers(topology)
    options = {"starts": 8, "max_iterations": 600, "coarse_to_fine": False,
               "ground_truth_mesh_to_world": cta.mesh_to_world.tolist()}
    with topology.api.client() as client:
        response = submit_volume(client, cta, options)
        assert response.status_code == 202, response.text
        job_id = response.json()["id"]
        deadline, job = time.monotonic() + 60, None
        while time.monotonic() < deadline:
            job = topology.store.get(job_id)
            if job.status == "running" and job.worker_id:
                break
            time.sleep(0.02)
        assert job is not None and job.status == "running", job
        victim = first if first.pid == pid_of_worker_id(job.worker_id) else second
        survivor = second if victim is first else first
        os.kill(victim.pid, signal.SIGSTOP)
        started = time.monotonic()
        assert client.get(f"/v1/registrations/{job_id}").status_code == 200
        assert time.monotonic() - started < allowed(2.0)  # answered while the worker is frozen
        time.sleep(5.0)  # past its 4-s lease
        victim.kill()  # SIGKILL, frozen as it is
        assert victim.process.poll() == -signal.SIGKILL  # reaped: no process left
        body = wait_for(client, job_id, timeout=240)
    assert body["status"] == "succeeded", (body, topology.logs())
    events = [e["event"] for e in topology.store.events(job_id)]
    assert events.count("succeeded") == 1 and "lease_expired" in events, events
    assert pid_of_worker_id(topology.store.get(job_id).worker_id) == survivor.pid
    key = volume_model_key(topology.store.get(job_id).inputs, engine.parse_options(options))
    with topology.store.engine.connect() as conn:
        rows = conn.execute(sa.text("SELECT count(*) FROM volume_models WHERE model_key = :key"), {"key": key}).scalar()
    assert rows == 1
    assert list((survivor.data_dir / "models").glob(".model-*.tmp")) == []
    assert (survivor.data_dir / "models" / f"{key}.npz").is_file()
