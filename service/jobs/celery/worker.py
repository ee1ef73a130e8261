"""Celery worker side: ``dsareg worker --engine celery`` runs :func:`run_worker`; each task claims
its job through the store's lease protocol and runs it with :func:`service.jobs.worker.run_one`.
"""

from __future__ import annotations

import logging
import os
import threading
from pathlib import Path
from typing import Any

from .app import TASK_NAME, make_celery
from ...engine_adapter import engine
from ...settings import ServiceSettings

log = logging.getLogger("dsareg.service.celery")


class _WorkerState:
    """What one Celery worker process keeps between tasks."""

    def __init__(self, settings: ServiceSettings):
        from ...storage.dbblobs import make_blob_store
        from ...storage.store import store_for
        from ..worker import DiskFloor, make_worker_id

        self.settings = settings
        self.store = store_for(settings)  # migrates the job database at start-up (under its lock)
        self.blobs = make_blob_store(settings, self.store.engine, cache=False)
        self.worker_id = make_worker_id(0)
        self.room = DiskFloor(settings)
        self.stop = threading.Event()  # set on warm shutdown: the running job is released
        self._beat = threading.Thread(target=self._seen_loop, name="worker-seen", daemon=True)
        self._beat.start()

    def _seen_loop(self) -> None:
        interval = max(1.0, self.settings.jobs.effective_heartbeat_seconds)
        while True:
            try:
                self.store.worker_seen(self.worker_id, os.getpid())
                # liveness file for container health checks (docker/compose.yaml)
                (Path(self.settings.storage.data_dir) / "worker-heartbeat").touch()
            except Exception:  # noqa: BLE001 - the store may be restarting
                log.warning("worker %s: store not reachable", self.worker_id)
            if self.stop.wait(interval):
                return


_STATE: _WorkerState | None = None
_STATE_LOCK = threading.Lock()


def _state(settings: ServiceSettings) -> _WorkerState:
    global _STATE
    with _STATE_LOCK:
        if _STATE is None:
            _STATE = _WorkerState(settings)
        return _STATE


def apply_thread_budget(settings: ServiceSettings) -> int:
    """Set torch's and numba's thread counts on *the calling thread*.

    Both are per-thread settings (numba's ``set_num_threads`` and the OpenMP ICV behind
    ``torch.set_num_threads`` belong to the thread that calls them); the ``threads`` pool runs
    tasks on a pool thread, where the main thread's setting does not apply and numba would take
    every core. Called at the start of every task, so it holds on whichever thread runs it.
    """
    try:
        return engine.set_cpu_threads(settings.jobs.threads_per_worker or engine.default_cpu_threads())
    except Exception:  # noqa: BLE001 - run with the defaults rather than not at all
        log.warning("could not set the task thread's CPU threads")
        return 0


def _run_job_task(self: Any, job_id: str) -> str:
    from sqlalchemy.exc import DBAPIError, OperationalError

    from ..worker import run_one

    settings: ServiceSettings = self.app.dsareg_settings
    state = _state(settings)
    apply_thread_budget(settings)
    if not state.room.check():  # no room for the outputs: leave it queued; the API's sweeper re-sends it
        log.info("job %s: left queued while the data disk is below its floor", job_id)
        return "deferred"
    try:
        job = state.store.claim_job(job_id, state.worker_id, settings.jobs.lease_seconds)
    except (OperationalError, DBAPIError) as exc:
        # the job store is briefly unreachable: bounded retries with backoff, then give up
        # (the job stays queued in the table and the API's sweeper re-sends it later)
        log.warning("job %s: claim failed (%s); retrying", job_id, type(exc).__name__)
        raise self.retry(exc=exc, countdown=min(30, 2 ** self.request.retries)) from None
    if job is None:
        log.info("job %s: not queued any more; message dropped", job_id)
        return "skipped"
    log.info("job %s: claimed by %s (attempt %d)", job.id, state.worker_id, job.attempts)

    def revoked() -> bool:
        from celery.worker import state as worker_state

        return job_id in worker_state.revoked

    outcome = run_one(state.store, state.blobs, job, state.worker_id, settings, state.stop, cancel_hint=revoked)
    if outcome == "released":  # warm shutdown: the job is queued again, hand it to another worker
        try:
            self.app.send_task(TASK_NAME, args=[job_id], task_id=job_id, queue=settings.celery.celery_queue)
        except Exception:  # noqa: BLE001 - the sweeper re-sends it
            log.warning("job %s: could not re-send after release", job_id)
    return outcome


def run_worker(settings: ServiceSettings, *, pool: str = "threads", hostname: str | None = None) -> None:
    """``dsareg worker --engine celery``: one Celery worker process running one job at a time."""
    if pool not in ("solo", "threads"):
        raise ValueError("pool must be 'solo' or 'threads'")
    try:
        import torch

        # set explicitly: several worker processes on one machine must not each take every core
        engine.set_cpu_threads(settings.jobs.threads_per_worker or engine.default_cpu_threads())
        torch.set_num_interop_threads(1)
    except Exception:  # noqa: BLE001
        log.warning("could not set the worker's CPU threads")
    from celery import signals

    from ..worker import warm_up

    warm_up(settings.jobs.warm_up_job)
    app = make_celery(settings, _run_job_task)
    state = _state(settings)

    @signals.worker_shutting_down.connect(weak=False)
    def _on_shutdown(**_: Any) -> None:
        state.stop.set()

    argv = ["worker", f"--pool={pool}", "--concurrency=1", "-Q", settings.celery.celery_queue,
            f"--loglevel={settings.server.log_level.upper()}", "--without-gossip", "--without-mingle"]
    if hostname:
        argv += ["-n", hostname]
    threads = settings.jobs.threads_per_worker or engine.default_cpu_threads()
    log.info("celery worker %s: pool %s, %d CPU threads", state.worker_id, pool, threads)
    try:
        app.worker_main(argv)
    finally:
        state.stop.set()
        state.store.dispose()
