"""The DICOM node as a whole: the C-STORE SCP, the durable inbox and the study dispatcher.

Two ways to run it (same settings, ``DSAREG_DICOM_*``):

* inside ``dsareg serve`` when ``DSAREG_DICOM_PORT`` is set (:func:`start_in_app`): jobs are
  submitted on the API's event loop with its validator, queue and executor;
* alone, ``dsareg dicom-listener`` (:func:`run_listener`), e.g. next to Celery workers: it opens
  the job database, the blob store, a validator process and the configured executor itself.

Only one listener per job database: at start it discards what associations of an earlier,
dead listener left uncommitted.
"""

from __future__ import annotations

import asyncio
import logging
import signal
import threading
from typing import Any

from .inbox import Inbox
from .jobs import StudyDispatcher
from .scp import StoreScp, start_server

log = logging.getLogger("dsareg.dimse")


class DicomListener:
    def __init__(self, ctx: Any, loop: asyncio.AbstractEventLoop):
        self.ctx = ctx
        store = ctx.store
        self.inbox = Inbox(store.engine, getattr(store, "writer", None))
        self.dispatcher = StudyDispatcher(ctx, self.inbox, loop, tick_seconds=min(0.25, ctx.settings.dicom_stable_seconds / 4),
                                          housekeeping=lambda: self.scp.sweep())
        self.scp = StoreScp(ctx.settings, self.inbox, ctx.blobs, on_commit=self.dispatcher.wake)
        self.server = None

    def start(self) -> None:
        orphans = self.inbox.discard_stale(live=set())
        if orphans:
            self.ctx.blobs.delete(orphans, min_age_seconds=0.0)
            log.warning("discarded %d instance file(s) of associations an earlier listener left open", len(orphans))
        self.dispatcher.start()
        self.server = start_server(self.ctx.settings, self.scp)
        settings = self.ctx.settings
        log.info("DICOM node %s listening on %s:%d (%d peers)", settings.dicom_ae_title, settings.dicom_host,
                 self.port, len(settings.dicom_peers))

    @property
    def port(self) -> int:
        return self.server.server_address[1] if self.server is not None else 0

    def stop(self) -> None:
        if self.server is not None:
            self.server.shutdown()
            self.server = None
        self.dispatcher.stop()


def start_in_app(ctx: Any) -> DicomListener | None:
    """The node of ``dsareg serve`` (None when ``dicom_port`` is unset); call from the running loop."""
    if not ctx.settings.dicom_port:
        return None
    listener = DicomListener(ctx, asyncio.get_running_loop())
    listener.start()
    return listener


def open_context(settings: Any) -> Any:
    """A service context for the listener's own process (no HTTP): store, blobs, validator, executor."""
    from prometheus_client import CollectorRegistry, Counter

    from ..api.deps import ServiceContext
    from ..dbblobs import make_blob_store
    from ..executor import NoExecutor
    from ..store import SqlJobStore
    from ..validation import ValidatorPool

    settings.data_dir.mkdir(parents=True, exist_ok=True)
    store = SqlJobStore(settings.effective_database_url)
    validator = ValidatorPool(settings.validation_processes, settings.validation_timeout_seconds,
                              settings.validation_memory_mb, threads=settings.threads_per_worker)
    validator.start()
    # embedded workers belong to `dsareg serve` (they poll the job table); Celery gets a message
    if settings.executor == "celery":
        from ..celery_executor import CeleryExecutor

        executor = CeleryExecutor(settings, store)
    else:
        executor = NoExecutor()
    registry = CollectorRegistry()
    return ServiceContext(settings=settings, store=store, blobs=make_blob_store(settings, store.engine),
                          validator=validator, executor=executor, registry=registry,
                          uploads=Counter("dsareg_dimse_upload_bytes", "unused", registry=registry))


def run_listener(settings: Any) -> int:
    """``dsareg dicom-listener``: the node in its own process, until SIGTERM / SIGINT."""
    import time

    if not settings.dicom_port:
        log.error("set DSAREG_DICOM_PORT (the listener's TCP port)")
        return 2
    ctx = open_context(settings)
    loop = asyncio.new_event_loop()
    loop_thread = threading.Thread(target=loop.run_forever, name="dimse-submit-loop", daemon=True)
    loop_thread.start()
    listener = DicomListener(ctx, loop)
    stopping = threading.Event()
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: stopping.set())
    try:
        deadline = time.monotonic() + settings.validation_timeout_seconds
        while not ctx.validator.ready() and time.monotonic() < deadline:
            time.sleep(0.1)
        ctx.executor.start()
        listener.start()
        print(f"dsareg dicom-listener: {settings.dicom_ae_title} on {settings.dicom_host}:{listener.port}", flush=True)
        stopping.wait()
    finally:
        listener.stop()
        loop.call_soon_threadsafe(loop.stop)
        loop_thread.join(5)
        ctx.executor.stop()
        ctx.validator.stop()
        ctx.store.dispose()
    return 0
