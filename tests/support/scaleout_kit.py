"""Real Redis / PostgreSQL (tests.support.servers) and Celery worker processes for the scale-out tests.

Environment overrides for CI machines that provide their own servers:
``DSAREG_TEST_REDIS_URL``, ``DSAREG_TEST_DATABASE_URL`` (tests that restart Redis then skip).
"""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

from tests.support.service_testkit import LoggedProcess, Server

from tests.support.servers import PostgresServer, RedisServer, free_port  # noqa: F401 - re-exported

REPO = Path(__file__).resolve().parents[2]


class CeleryWorker(LoggedProcess):
    """``python -m service worker --engine celery`` as a separate process."""

    def __init__(self, name: str, data_dir: Path, env: dict[str, str], pool: str = "threads"):
        self.name = name
        self.data_dir = Path(data_dir)
        self.env = env
        self.pool = pool
        self.process: subprocess.Popen | None = None
        self.log_path = self.data_dir.parent / f"{name}.log"

    def start(self) -> CeleryWorker:
        self.data_dir.mkdir(parents=True, exist_ok=True)
        self.log = open(self.log_path, "ab")  # noqa: SIM115
        env = {**os.environ, "PYTHONUNBUFFERED": "1", **self.env}
        self.process = subprocess.Popen(
            [sys.executable, "-m", "service", "worker", "--engine", "celery", "--pool", self.pool,
             "--hostname", f"{self.name}@%h", "--data-dir", str(self.data_dir)],
            cwd=REPO, env=env, stdout=self.log, stderr=subprocess.STDOUT, start_new_session=True)
        return self

    @property
    def pid(self) -> int | None:
        return None if self.process is None else self.process.pid


def pid_of_worker_id(worker_id: str) -> int:
    """``<host>-<pid>-w<index>-<token>`` (see service.jobs.worker.make_worker_id)."""
    return int(worker_id.rsplit("-", 3)[1])


class CeleryTopology:
    """The scale-out topology on loopback: the API (no embedded workers) + Celery workers, sharing
    ``redis`` and ``postgres`` (blobs in the database, short leases so faults show quickly)."""

    def __init__(self, root: Path, redis, postgres):
        from service.storage.store import SqlJobStore

        self.root, self.redis, self.postgres = root, redis, postgres
        self.env = {
            "DSAREG_EXECUTOR": "celery", "DSAREG_BROKER_URL": redis.url, "DSAREG_DATABASE_URL": postgres.url,
            "DSAREG_BLOB_BACKEND": "database", "DSAREG_THREADS_PER_WORKER": "1", "DSAREG_LEASE_SECONDS": "4",
            "DSAREG_REDISPATCH_AFTER_SECONDS": "3", "DSAREG_BROKER_VISIBILITY_TIMEOUT_SECONDS": "20",
            "DSAREG_PROGRESS_INTERVAL_SECONDS": "0.2", "DSAREG_WARM_UP_JOB": "0",  # as service_testkit.Server's
        }
        self.api = Server(root / "api", workers=0, env=self.env)
        self.workers: list[CeleryWorker] = []
        self.count = 0
        self.store = SqlJobStore(postgres.url, create_schema=True)

    def add_worker(self) -> CeleryWorker:
        self.count += 1
        worker = CeleryWorker(f"w{self.count}", self.root / f"w{self.count}", self.env).start()
        self.workers.append(worker)
        return worker

    def wait_workers(self, n: int, timeout: float = 90.0) -> None:
        deadline = time.monotonic() + timeout
        with self.api.client() as client:
            while time.monotonic() < deadline:
                response = client.get("/readyz")
                if response.status_code == 200 and response.json().get("checks", {}).get("workers_alive", 0) >= n:
                    return
                time.sleep(0.3)
        raise AssertionError(f"{n} workers not alive after {timeout} s")

    def stop_workers(self) -> None:
        for worker in self.workers:
            worker.stop()
        self.workers = []

    def events_of(self, job_id: str) -> list[str]:
        return [e["event"] for e in self.store.events(job_id)]

    def status_of(self, job_id: str) -> str:
        job = self.store.get(job_id)
        return "missing" if job is None else job.status

    def logs(self) -> str:
        return "\n".join(w.logs()[-2500:] for w in self.workers) + "\n" + self.api.logs()[-3000:]
