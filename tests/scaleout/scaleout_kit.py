"""Real Redis / PostgreSQL (service.bench.servers) and Celery worker processes for the scale-out tests.

Environment overrides for CI machines that provide their own servers:
``DSAREG_TEST_REDIS_URL``, ``DSAREG_TEST_DATABASE_URL`` (tests that restart Redis then skip).
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

from service_testkit import LoggedProcess

from service.bench.servers import PostgresServer, RedisServer, free_port  # noqa: F401 - re-exported

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
    """``<host>-<pid>-w<index>-<token>`` (see service.worker.make_worker_id)."""
    return int(worker_id.rsplit("-", 3)[1])
