"""Celery executor (API side): jobs run on Celery workers (``dsareg worker --engine celery``) behind a broker.

The job table stays the single record of each job's state. A Celery message is only a
*hint* "job <id> is runnable": the worker that receives it claims the job with the
store's lease protocol (conditional UPDATE … WHERE status='queued'). So

* a message delivered twice (re-dispatch, broker redelivery after a worker died) finds
  the job running or finished and is dropped: a job runs to completion at most once,
  because completion is guarded by ``worker_id`` (see :mod:`service.storage.leases`);
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
import threading
import time
from typing import TYPE_CHECKING, Any

from .app import TASK_NAME, make_celery
from ..executor import Executor
from ...settings import ServiceSettings

if TYPE_CHECKING:
    from ...storage.interfaces import Leases, Upkeep

log = logging.getLogger("dsareg.service.celery")


class CeleryExecutor(Executor):
    """Submits and cancels through Celery; workers are separate processes/machines."""

    def __init__(self, settings: ServiceSettings, store: Leases | None = None):
        self.settings = settings
        self.store = store
        self.app = make_celery(settings)
        self.dispatched: dict[str, float] = {}
        self.redispatched = 0
        self._last_maintain = 0.0
        self._lock = threading.Lock()

    def start(self) -> None:
        log.info("celery executor: queue %s", self.settings.celery.celery_queue)

    def stop(self, timeout: float = 10.0) -> None:
        try:
            self.app.pool.force_close_all()
        except Exception:  # shutting down anyway
            log.debug("closing broker connections failed", exc_info=True)

    def notify(self) -> None:
        pass

    def _send(self, job_id: str) -> bool:
        try:
            self.app.send_task(TASK_NAME, args=[job_id], task_id=job_id, queue=self.settings.celery.celery_queue)
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
                        queue=self.settings.celery.celery_queue, passive=True).message_count)
                except conn.connection_errors:
                    return None
                except Exception:  # noqa: BLE001 - the queue does not exist (e.g. after a broker restart)
                    return 0
        except Exception:  # noqa: BLE001 - broker unreachable
            return None

    def maintain(self, store: Upkeep) -> None:
        """Re-send queued jobs the broker may have lost (the job table is the truth).

        A queued job that nobody claimed for ``redispatch_after_seconds`` is sent again when the
        broker's queue holds fewer messages than there are queued jobs (so a normally busy queue
        is not flooded with duplicates). Duplicates are harmless: the claim decides.
        """
        now = time.time()
        after = self.settings.celery.redispatch_after_seconds
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
        window = max(10.0, 3.0 * max(1.0, self.settings.jobs.effective_heartbeat_seconds))
        try:
            return self.store.live_workers(time.time() - window)
        except Exception:  # noqa: BLE001
            return 0

    def describe(self) -> dict[str, Any]:
        return {"kind": "celery", "alive_workers": self.alive_workers(), "queue": self.settings.celery.celery_queue,
                "redispatched": self.redispatched}
