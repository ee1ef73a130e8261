"""The app's lifespan: open the store, start the validators, the executor and the sweeper; stop them."""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import threading
import time
from collections.abc import Callable
from typing import Any

from fastapi import FastAPI

from ..callbacks import CallbackDeliverer
from ..dbblobs import make_blob_store
from ..executor import Executor
from ..settings import ServiceSettings
from ..store import SqlJobStore, store_outage_errors
from ..validation import ValidatorPool
from ..models import summary_body
from .deps import ServiceContext
from .metrics import ServiceMetrics

log = logging.getLogger("dsareg.service")


class Sweeper:
    """Recovers expired leases (often) and enforces retention (every sweep interval).

    After the job store was unreachable, no lease is judged expired for one lease period: while
    the database was down no worker could renew its lease, so an expired lease is no sign of a
    dead worker, and requeuing would throw away a registration its worker is about to save.
    """

    def __init__(self, ctx: ServiceContext):
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
        recovery_every = max(0.5, min(5.0, self.ctx.settings.lease_seconds / 3.0))
        while not self._halt.wait(recovery_every):
            try:
                self.sweep_once(recover=time.monotonic() >= self.recover_after)
            except store_outage_errors() as exc:
                log.warning("sweep skipped: job store unavailable (%s)", type(exc).__name__)
                self.recover_after = time.monotonic() + self.ctx.settings.lease_seconds
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
        if force_retention or now - self.last_retention >= self.ctx.settings.sweep_interval_seconds:
            self.last_retention = now
            self._retention(now)

    def _retention(self, now: float) -> None:
        store, blobs, settings = self.ctx.store, self.ctx.blobs, self.ctx.settings
        expired = store.expired_finished(now - settings.retention_hours * 3600.0)
        for job_id in expired:
            orphans = store.delete(job_id)
            blobs.delete(orphans, min_age_seconds=0.0)  # submit re-stores a blob it still needs
            blobs.remove_job_work(job_id)
        if expired:
            log.info("retention: removed %d jobs", len(expired))
        blobs.collect_garbage(store.referenced_blobs(), min_age_seconds=3600.0)
        blobs.clean_tmp()


def _open_context(settings: ServiceSettings, metrics: ServiceMetrics, executor: Executor | None,
                  make_executor: Callable[[ServiceSettings, Any], Executor], start_background: bool) -> ServiceContext:
    settings.data_dir.mkdir(parents=True, exist_ok=True)
    store = SqlJobStore(settings.effective_database_url)
    blobs = make_blob_store(settings, store.engine)
    validator = None
    if start_background:
        validator = ValidatorPool(settings.validation_processes, settings.validation_timeout_seconds,
                                  settings.validation_memory_mb, threads=settings.threads_per_worker)
        validator.start()
    ex = executor or make_executor(settings, store)
    return ServiceContext(settings=settings, store=store, blobs=blobs, validator=validator, executor=ex,
                          registry=metrics.registry, uploads=metrics.uploads)


def callback_body(job: Any) -> bytes:
    """A callback's body: the job summary (``JobSummary``) as compact JSON."""
    return json.dumps(summary_body(job), separators=(",", ":")).encode("utf-8")


def start_callbacks(ctx: ServiceContext) -> CallbackDeliverer:
    """The completion-callback deliverer of this API process (service/callbacks.py), in every topology."""
    from .. import __version__

    deliverer = CallbackDeliverer(ctx.store, ctx.settings, callback_body, user_agent=f"dsareg/{__version__}")
    deliverer.start()
    return deliverer


def make_lifespan(settings: ServiceSettings, metrics: ServiceMetrics, holder: dict[str, ServiceContext | None], *,
                  executor: Executor | None, make_executor: Callable[[ServiceSettings, Any], Executor],
                  start_background: bool):
    """The lifespan context manager; ``holder['ctx']`` is the running context (for the metrics collector)."""

    @contextlib.asynccontextmanager
    async def lifespan(app: FastAPI):
        ctx = _open_context(settings, metrics, executor, make_executor, start_background)
        holder["ctx"] = ctx
        app.state.ctx = ctx
        if not settings.auth_enabled:
            log.warning("no API keys configured: authentication is off and the service listens on 127.0.0.1 only")
        if start_background:
            ctx.executor.start()
            ctx.sweeper = Sweeper(ctx)
            ctx.sweeper.sweep_once()
            ctx.sweeper.start()
            ctx.callbacks = start_callbacks(ctx)
        log.info("dsareg service ready (%d worker processes, store %s)", settings.workers,
                 "sqlite" if ctx.store.is_sqlite else ctx.store.engine.dialect.name)
        try:
            yield
        finally:
            if ctx.callbacks:
                ctx.callbacks.stop()
            if ctx.sweeper:
                ctx.sweeper.stop()
            await asyncio.to_thread(ctx.executor.stop)
            if ctx.validator:
                await asyncio.to_thread(ctx.validator.stop)
            ctx.store.dispose()
            holder["ctx"] = None

    return lifespan
