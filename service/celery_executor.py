"""Celery executor: jobs run on Celery workers (``dsareg worker --engine celery``) behind a broker.

The job table stays the single record of each job's state. A Celery message is only a
*hint* "job <id> is runnable": the worker that receives it claims the job with the
store's lease protocol (conditional UPDATE … WHERE status='queued'). So

* a message delivered twice (re-dispatch, broker redelivery after a worker died) finds
  the job running or finished and is dropped: a job runs to completion at most once,
  because completion is guarded by ``worker_id`` (see :mod:`service.store`);
* a message the broker lost (Redis restarted without persistence) is re-sent by the
  API's sweeper (:meth:`CeleryExecutor.maintain`): queued rows are the truth;
* a worker killed mid-job stops renewing its lease; the sweeper requeues the job and
  re-sends it, another worker claims it (attempt 2). The dead worker's unacked message is
  redelivered by Redis after the visibility timeout and then finds the job finished.

Cancellation: the API sets the job's ``cancel_requested`` flag (read by the worker's
heartbeat thread) *and* revokes the task (task id = job id): a revoked message still in
the queue is discarded, and with the ``threads`` pool the running task sees the
revocation at once (the engine's ``should_stop`` checks it) instead of at the next beat.
"""

from __future__ import annotations

import logging
import os
import threading
import time
from pathlib import Path
from typing import Any

from dsareg_engine.threads import default_cpu_threads

from .executor import Executor
from .settings import ServiceSettings

log = logging.getLogger("dsareg.service.celery")

TASK_NAME = "dsareg.run_job"


def celery_config(settings: ServiceSettings) -> dict[str, Any]:
    """Celery settings, each with the reason it is there."""
    timeout = settings.job_timeout_seconds
    vt = settings.effective_visibility_timeout
    return {
        "broker_url": settings.broker_url,
        # nothing reads Celery results: the job table holds them
        "task_ignore_result": True,
        "result_backend": None,
        "task_serializer": "json",
        "accept_content": ["json"],
        "task_default_queue": settings.celery_queue,
        # ack only after the task returned: a worker that dies mid-job leaves its message
        # unacked, so the broker delivers it again instead of forgetting the job
        "task_acks_late": True,
        # when a pool child is killed (OOM killer, SIGKILL) requeue the message rather than
        # acking it as failed (prefork pool; with solo/threads the whole process dies and the
        # message stays unacked anyway)
        "task_reject_on_worker_lost": True,
        # a worker reserves only the job it runs (with acks_late the running message counts):
        # registrations take seconds to minutes, so prefetched messages would wait behind a
        # long job while another worker is idle
        "worker_prefetch_multiplier": 1,
        # Redis redelivers a message not acked within the visibility timeout. It must be longer
        # than the longest job, else a healthy long job is delivered to a second worker (which
        # would then find it running and drop it — harmless but noisy). Worker death is
        # detected much sooner by the job lease; this is only the broker's fallback.
        # The sweep that restores expired unacked messages runs every interval * throttle seconds
        # (kombu default 10 * 10); a scan every interval (at most 10 s) is cheap (one ZRANGE).
        "broker_transport_options": {
            "visibility_timeout": int(vt),
            "unacked_restore_interval": max(1, min(10, int(vt / 4))),
            "unacked_restore_throttle": 1,
            "socket_connect_timeout": 5,
        },
        # time limits a bit above the engine's own job timeout (which the worker enforces
        # through should_stop and reports as a clean 'failed' job). Celery enforces these only
        # with the prefork pool; with solo/threads the job timeout is the limit.
        "task_soft_time_limit": int(timeout + 120),
        "task_time_limit": int(timeout + 300),
        # publishing must not hang a request when the broker is down: a couple of quick
        # retries, then the job stays queued in the table and the sweeper re-sends it
        "task_publish_retry": True,
        "task_publish_retry_policy": {"max_retries": 2, "interval_start": 0, "interval_step": 0.2, "interval_max": 0.5},
        "broker_connection_timeout": 2.0,
        "broker_connection_retry_on_startup": True,
        "broker_connection_max_retries": None,  # a worker keeps trying while Redis restarts
        "worker_cancel_long_running_tasks_on_connection_loss": False,  # the lease protects the job
        "worker_hijack_root_logger": False,
        "worker_send_task_events": False,
        "task_track_started": False,
    }


def make_celery(settings: ServiceSettings):
    from celery import Celery

    app = Celery("dsareg", set_as_current=False)
    app.conf.update(celery_config(settings))
    app.task(name=TASK_NAME, bind=True, acks_late=True, reject_on_worker_lost=True,
             max_retries=settings.task_max_retries)(_run_job_task)
    app.dsareg_settings = settings
    return app


# ---- worker side ------------------------------------------------------------------------------


class _WorkerState:
    """What one Celery worker process keeps between tasks."""

    def __init__(self, settings: ServiceSettings):
        from .dbblobs import make_blob_store
        from .store import SqlJobStore
        from .worker import make_worker_id

        self.settings = settings
        self.store = SqlJobStore(settings.effective_database_url, create_schema=False)
        self.blobs = make_blob_store(settings, self.store.engine, cache=False)
        self.worker_id = make_worker_id(0)
        self.stop = threading.Event()  # set on warm shutdown: the running job is released
        self._beat = threading.Thread(target=self._seen_loop, name="worker-seen", daemon=True)
        self._beat.start()

    def _seen_loop(self) -> None:
        interval = max(1.0, self.settings.effective_heartbeat_seconds)
        while True:
            try:
                self.store.worker_seen(self.worker_id, os.getpid())
                # liveness file for container health checks (docker/compose.yaml)
                (Path(self.settings.data_dir) / "worker-heartbeat").touch()
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
        from dsareg_engine.threads import set_cpu_threads

        return set_cpu_threads(settings.threads_per_worker or default_cpu_threads())
    except Exception:  # noqa: BLE001 - run with the defaults rather than not at all
        log.warning("could not set the task thread's CPU threads")
        return 0


def _run_job_task(self: Any, job_id: str) -> str:
    from sqlalchemy.exc import DBAPIError, OperationalError

    from .worker import run_one

    settings: ServiceSettings = self.app.dsareg_settings
    state = _state(settings)
    apply_thread_budget(settings)
    try:
        job = state.store.claim_job(job_id, state.worker_id, settings.lease_seconds)
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
            self.app.send_task(TASK_NAME, args=[job_id], task_id=job_id, queue=settings.celery_queue)
        except Exception:  # noqa: BLE001 - the sweeper re-sends it
            log.warning("job %s: could not re-send after release", job_id)
    return outcome


def run_worker(settings: ServiceSettings, *, pool: str = "threads", hostname: str | None = None) -> None:
    """``dsareg worker --engine celery``: one Celery worker process running one job at a time."""
    if pool not in ("solo", "threads"):
        raise ValueError("pool must be 'solo' or 'threads'")
    try:
        import torch

        from dsareg_engine.threads import set_cpu_threads

        # set explicitly: several worker processes on one machine must not each take every core
        set_cpu_threads(settings.threads_per_worker or default_cpu_threads())
        torch.set_num_interop_threads(1)
    except Exception:  # noqa: BLE001
        log.warning("could not set the worker's CPU threads")
    from celery import signals

    from .worker import warm_up

    warm_up()
    app = make_celery(settings)
    state = _state(settings)

    @signals.worker_shutting_down.connect(weak=False)
    def _on_shutdown(**_: Any) -> None:
        state.stop.set()

    argv = ["worker", f"--pool={pool}", "--concurrency=1", "-Q", settings.celery_queue,
            f"--loglevel={settings.log_level.upper()}", "--without-gossip", "--without-mingle"]
    if hostname:
        argv += ["-n", hostname]
    log.info("celery worker %s: pool %s, %d CPU threads", state.worker_id, pool, settings.threads_per_worker or default_cpu_threads())
    try:
        app.worker_main(argv)
    finally:
        state.stop.set()
        state.store.dispose()


# ---- API side ---------------------------------------------------------------------------------


class CeleryExecutor(Executor):
    """Submits and cancels through Celery; workers are separate processes/machines."""

    def __init__(self, settings: ServiceSettings, store: Any = None):
        self.settings = settings
        self.store = store
        self.app = make_celery(settings)
        self.dispatched: dict[str, float] = {}
        self.redispatched = 0
        self._last_maintain = 0.0
        self._lock = threading.Lock()

    def start(self) -> None:
        log.info("celery executor: queue %s", self.settings.celery_queue)

    def stop(self, timeout: float = 10.0) -> None:
        try:
            self.app.pool.force_close_all()
        except Exception:  # shutting down anyway
            log.debug("closing broker connections failed", exc_info=True)

    def notify(self) -> None:
        pass

    def _send(self, job_id: str) -> bool:
        try:
            self.app.send_task(TASK_NAME, args=[job_id], task_id=job_id, queue=self.settings.celery_queue)
        except Exception as exc:  # noqa: BLE001 - the job is safe in the table; the sweeper re-sends it
            log.warning("job %s: broker unreachable (%s); will re-send", job_id, type(exc).__name__)
            return False
        with self._lock:
            self.dispatched[job_id] = time.time()
        return True

    def submit(self, job_id: str) -> None:
        self._send(job_id)

    def cancel(self, job_id: str) -> None:
        try:
            self.app.control.revoke(job_id)
        except Exception as exc:  # noqa: BLE001 - the job table flag still reaches the worker
            log.warning("job %s: revoke not sent (%s)", job_id, type(exc).__name__)

    def requeued(self, job_ids: list[str]) -> None:
        for job_id in job_ids:
            self._send(job_id)

    def broker_queue_length(self) -> int | None:
        """Messages waiting in the broker's queue (None when the broker cannot be asked)."""
        try:
            with self.app.connection_for_write() as conn:
                conn.ensure_connection(max_retries=1)
                try:
                    return int(conn.default_channel.queue_declare(
                        queue=self.settings.celery_queue, passive=True).message_count)
                except conn.connection_errors:
                    return None
                except Exception:  # noqa: BLE001 - the queue does not exist (e.g. after a broker restart)
                    return 0
        except Exception:  # noqa: BLE001 - broker unreachable
            return None

    def maintain(self, store: Any) -> None:
        """Re-send queued jobs the broker may have lost (the job table is the truth).

        A queued job that nobody claimed for ``redispatch_after_seconds`` is sent again when the
        broker's queue holds fewer messages than there are queued jobs (so a normally busy queue
        is not flooded with duplicates). Duplicates are harmless: the claim decides.
        """
        now = time.time()
        after = self.settings.redispatch_after_seconds
        if now - self._last_maintain < min(10.0, after / 2.0):
            return
        self._last_maintain = now
        with self._lock:
            self.dispatched = {k: t for k, t in self.dispatched.items() if now - t < after}
            recent = set(self.dispatched)
        stale = [job_id for job_id in store.queued_since(now - after) if job_id not in recent]
        if not stale:
            return
        waiting = self.broker_queue_length()
        if waiting is None:  # broker down: try again next round (do not stall the sweeper on timeouts)
            return
        if waiting >= store.queued_count():
            return
        sent = 0
        for job_id in stale:
            if not self._send(job_id):
                break
            sent += 1
        self.redispatched += sent
        if sent:
            log.warning("re-dispatched %d queued jobs to the broker", sent)

    def alive_workers(self) -> int:
        if self.store is None:
            return 0
        window = max(10.0, 3.0 * max(1.0, self.settings.effective_heartbeat_seconds))
        try:
            return self.store.live_workers(time.time() - window)
        except Exception:  # noqa: BLE001
            return 0

    def describe(self) -> dict[str, Any]:
        return {"kind": "celery", "alive_workers": self.alive_workers(), "queue": self.settings.celery_queue,
                "redispatched": self.redispatched}
