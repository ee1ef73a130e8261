"""The app's lifespan: open the store, start the validators, the executor and the sweeper; stop them."""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
from collections.abc import Callable
from typing import Any

from fastapi import FastAPI

from ..jobs.callbacks import CallbackDeliverer
from ..jobs.exports import ExportDeliverer
from ..intake.context import close_intake
from ..pacs.dimse.listener import DicomListener
from ..jobs.executor import Executor
from ..settings import ServiceSettings
from ..storage.owners import ANONYMOUS, count_by_owner
from ..jobs.sweeper import Sweeper
from .schemas.jobs import summary_body
from .deps import ServiceContext
from .prometheus import ServiceMetrics

log = logging.getLogger("dsareg.service")


def _open_context(settings: ServiceSettings, metrics: ServiceMetrics, executor: Executor | None,
                  make_executor: Callable[[ServiceSettings, Any], Executor], start_background: bool) -> ServiceContext:
    return ServiceContext.open(settings, lambda s, store: executor or make_executor(s, store),
                               validate=start_background, registry=metrics.registry, uploads=metrics.uploads)


def callback_body(job: Any) -> bytes:
    """A callback's body: the job summary (``JobSummary``) as compact JSON."""
    return json.dumps(summary_body(job), separators=(",", ":")).encode("utf-8")


def start_callbacks(ctx: ServiceContext) -> CallbackDeliverer:
    """The completion-callback deliverer of this API process (service/jobs/callbacks.py), in every topology."""
    from .. import __version__

    deliverer = CallbackDeliverer(ctx.store, ctx.settings, callback_body, user_agent=f"dsareg/{__version__}")
    deliverer.start()
    return deliverer


def _start_dicom_node(ctx: ServiceContext) -> DicomListener | None:
    """The DICOM node of ``dsareg serve`` when ``DSAREG_DICOM_PORT`` is set (its jobs go through this API's intake)."""
    if not ctx.settings.dimse.dicom_port:
        return None
    listener = DicomListener(ctx, asyncio.get_running_loop())
    listener.start()
    return listener


def no_keys_warning(settings: ServiceSettings) -> str:
    """The one start-up line of a server without API keys (``dsareg serve`` logged a second one when it moved a
    ``--host`` to loopback)."""
    asked = settings.server.host
    moved = f" (not {asked}: serving other machines needs API keys)" if asked != settings.effective_host else ""
    return f"no API keys configured: authentication is off and the service listens on 127.0.0.1 only{moved}"


def warn_hidden_jobs(ctx: ServiceContext) -> None:
    """With API keys on, the jobs made while they were off (owner ``anonymous``) answer 404 to every key: say so
    at start, and how to hand them to a key (service/cli/jobs.py)."""
    hidden = count_by_owner(ctx.store.engine).get(ANONYMOUS, 0)
    if hidden:
        log.warning("%d job(s) made while no API keys were configured are hidden from every key (each key sees only "
                    "its own jobs); `dsareg jobs assign --to-key-hash DIGEST` gives them to one key", hidden)


def make_lifespan(settings: ServiceSettings, metrics: ServiceMetrics, holder: dict[str, ServiceContext | None], *,
                  executor: Executor | None, make_executor: Callable[[ServiceSettings, Any], Executor],
                  start_background: bool):
    """The lifespan context manager; ``holder['ctx']`` is the running context (for the metrics collector)."""

    @contextlib.asynccontextmanager
    async def lifespan(app: FastAPI):
        ctx = _open_context(settings, metrics, executor, make_executor, start_background)
        holder["ctx"] = ctx
        app.state.ctx = ctx
        if not settings.auth.auth_enabled:
            log.warning(no_keys_warning(settings))
        else:
            warn_hidden_jobs(ctx)
        if start_background:
            # the DICOM packages are imported whole here, before the background threads: a thread importing
            # pydicom while another imports it (or pynetdicom) can be handed a half-initialised module
            import pydicom  # noqa: F401
            import pynetdicom  # noqa: F401

            ctx.executor.start()
            ctx.sweeper = Sweeper(ctx)
            ctx.sweeper.sweep_once()
            ctx.sweeper.start()
            ctx.callbacks = start_callbacks(ctx)
            ctx.extra["exports"] = ExportDeliverer(ctx.store, ctx.blobs, ctx.settings)  # every PACS export
            ctx.extra["exports"].start()
            ctx.extra["dicom_listener"] = _start_dicom_node(ctx)
        log.info("dsareg service ready (%d worker processes, store %s)", settings.jobs.workers,
                 "sqlite" if ctx.store.is_sqlite else ctx.store.engine.dialect.name)
        try:
            yield
        finally:
            if ctx.callbacks:
                ctx.callbacks.stop()
            if ctx.extra.get("exports") is not None:
                ctx.extra["exports"].stop()
            if ctx.extra.get("dicom_listener") is not None:
                await asyncio.to_thread(ctx.extra["dicom_listener"].stop)
            if ctx.sweeper:
                ctx.sweeper.stop()
            await asyncio.to_thread(close_intake, ctx)
            holder["ctx"] = None

    return lifespan
