"""The lease and retention sweeper: a thread of the API process that requeues jobs whose lease expired and
removes finished jobs past the retention period (and unreferenced blobs)."""

from __future__ import annotations

import logging
import threading
import time
from typing import Protocol

from ..settings import ServiceSettings
from ..storage.blobs import BlobStore
from ..storage.interfaces import Upkeep
from ..storage.store import store_outage_errors
from .executor import Executor

log = logging.getLogger("dsareg.service")


class SweptService(Protocol):
    """What the sweeper reads (the API's ``ServiceContext`` is one); attributes are read on every sweep."""

    settings: ServiceSettings
    store: Upkeep
    blobs: BlobStore
    executor: Executor


class Sweeper:
    """Recovers expired leases (often) and enforces retention (every sweep interval).

    After the job store was unreachable, no lease is judged expired for one lease period: while
    the database was down no worker could renew its lease, so an expired lease is no sign of a
    dead worker, and requeuing would throw away a registration its worker is about to save.
    """

    def __init__(self, ctx: SweptService):
        self.ctx = ctx
        self._halt = threading.Event()
        self._thread = threading.Thread(target=self._run, name="sweeper", daemon=True)
        self.last_retention = 0.0
        self.recover_after = 0.0  # monotonic time before which leases are not recovered (store outage grace)

    def start(self) -> None:
        self._thread.start()

    def stop(self) -> None:
        self._halt.set()
        self._thread.join(5)

    def _run(self) -> None:
        recovery_every = max(0.5, min(5.0, self.ctx.settings.jobs.lease_seconds / 3.0))
        while not self._halt.wait(recovery_every):
            try:
                self.sweep_once(recover=time.monotonic() >= self.recover_after)
            except store_outage_errors() as exc:
                log.warning("sweep skipped: job store unavailable (%s)", type(exc).__name__)
                self.recover_after = time.monotonic() + self.ctx.settings.jobs.lease_seconds
            except Exception:
                log.exception("sweep failed")

    def sweep_once(self, *, force_retention: bool = False, recover: bool = True) -> None:
        store = self.ctx.store
        requeued, failed = store.recover_expired() if recover else ([], [])
        for job_id in requeued:
            log.warning("job %s: lease expired, requeued", job_id)
        for job_id in failed:
            log.warning("job %s: lease expired, no attempts left (or canceled)", job_id)
        self.ctx.executor.requeued(requeued)
        self.ctx.executor.maintain(store)
        now = time.time()
        if force_retention or now - self.last_retention >= self.ctx.settings.retention.sweep_interval_seconds:
            self.last_retention = now
            self._retention(now)

    def _retention(self, now: float) -> None:
        store, blobs, settings = self.ctx.store, self.ctx.blobs, self.ctx.settings
        expired = store.expired_finished(now - settings.retention.retention_hours * 3600.0)
        for job_id in expired:
            orphans = store.delete(job_id)
            blobs.delete(orphans, min_age_seconds=0.0)  # submit re-stores a blob it still needs
            blobs.remove_job_work(job_id)
        if expired:
            log.info("retention: removed %d jobs", len(expired))
        blobs.collect_garbage(store.referenced_blobs())  # UNNAMED_FILE_AGE_S old
        blobs.clean_tmp()
