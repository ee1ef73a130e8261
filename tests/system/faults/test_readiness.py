"""/readyz tells the truth about warm-up: a worker that is alive but still warming up (compiling the
kernels: minutes on a fresh install) does not make the node ready; once it is ready, a job starts at once.

The warming worker is frozen (SIGSTOP) right after it starts, so the test does not depend on how long a
cold compile takes on the machine running it; SIGCONT lets it finish."""

from __future__ import annotations

import os
import signal
import time
from pathlib import Path

import httpx
import pytest
from tests.support.faults_kit import descendants
from tests.support.service_testkit import Server, needs_engine, submit, wait_for
from tests.support.time_bounds import allowed

pytestmark = [needs_engine, pytest.mark.slow]

FAST = {"starts": 1, "max_iterations": 10}


def _named(root_pid: int, name: str) -> list[int]:
    """Live children of ``root_pid`` whose kernel name (``/proc/<pid>/comm``) is ``name`` (not grandchildren: a child
    a worker forks carries the worker's name until it execs)."""
    found = []
    for pid in descendants(root_pid):
        try:
            parent = int(Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[1])
            if parent == root_pid and Path(f"/proc/{pid}/comm").read_text().strip() == name:
                found.append(pid)
        except OSError:
            pass
    return found


def _wait(predicate, timeout: float, what: str):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = predicate()
        if value:
            return value
        time.sleep(0.05)
    raise AssertionError(f"not within {timeout} s: {what}")


def test_readyz_is_503_while_the_worker_warms_up_and_a_job_starts_at_once_after(tmp_path, case):
    srv = Server(tmp_path / "data", workers=1, env={"DSAREG_WARM_UP_JOB": "1"}).start(wait_ready=False)  # the default
    worker = None
    try:
        (worker,) = _wait(lambda: _named(srv.process.pid, "dsareg-worker0"), 60, "the worker process to start")
        os.kill(worker, signal.SIGSTOP)  # frozen mid-warm-up, before it registered as ready
        assert _named(srv.process.pid, "dsareg-validate"), "the validator names itself too"
        with httpx.Client(base_url=srv.url, timeout=5) as client:
            body = _wait(lambda: (r := client.get("/readyz")).json()["checks"]["validator_ready"] and r,
                         90, "the validator to be ready").json()
            response = client.get("/readyz")
            assert response.status_code == 503, f"ready while the only worker is still warming up: {response.json()}"
            checks = response.json()["checks"]
            assert checks["workers_alive"] == 1 and checks["workers_ready"] == 0, checks
            assert "warming" in checks and "compiling" in checks["warming"], checks
            assert response.headers.get("Retry-After")

            os.kill(worker, signal.SIGCONT)
            _wait(lambda: client.get("/readyz").status_code == 200, 240, "/readyz 200 after the warm-up")
            assert client.get("/readyz").json()["checks"]["workers_ready"] == 1
        with srv.client() as client:
            submitted = time.time()
            response = submit(client, case, FAST)
            assert response.status_code == 202, response.text
            job = wait_for(client, response.json()["id"], statuses=("running", "succeeded"), timeout=30)
            started = job["started_at"]
        from datetime import datetime

        started_s = datetime.fromisoformat(started.replace("Z", "+00:00")).timestamp()
        assert started_s - submitted <= allowed(5.0), f"the job waited {started_s - submitted:.1f} s after /readyz said ready"
        assert "warmed up in" in srv.logs() and "warming up" in srv.logs()
        assert "kernels only" not in srv.logs(), "the production default warms up with a job"
    finally:
        if worker is not None:
            try:
                os.kill(worker, signal.SIGCONT)
            except ProcessLookupError:
                pass
        srv.stop()
