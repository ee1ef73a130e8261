"""The HTTP API (FastAPI): long-running-operation pattern over the job store.

``create_app(settings)`` wires the app together from :mod:`service.api`: the lifespan
(store, input-validator processes, executor, sweeper), metrics, error handlers, one router
per resource, the offline docs and the OpenAPI patches.
"""

from __future__ import annotations


from fastapi import FastAPI

from . import __version__
from .api.routes import artifacts, events, hemodynamics, operations, registrations, review, tracking, ui
from .api.deps import ServiceContext
from .api.handlers import install_handlers
from .api.httpdeadlines import BodyDeadlineMiddleware, HttpDeadlines, with_header_deadline
from .api.httpfaults import problem_http_protocol
from .api.lifespan import make_lifespan
from .api.prometheus import make_metrics
from .api.openapi import install_openapi, mount, operation_id
from .api.docs_offline import install_docs
from .jobs.executor import Executor
from .jobs.factory import make_executor
from .api.middleware import BodyLimitMiddleware, MetricsMiddleware
from .problems import problem_responses
from .settings import ServiceSettings

DESCRIPTION = (
    "Registers a 3D vessel model to biplane DSA images. Submit a job with `POST /v1/registrations` "
    "(multipart files, or JSON with the inputs by DICOMweb reference), poll the `Location` it returns (or give a "
    "`callback_url`), then fetch the result and overlays.\n\n"
    "**`succeeded` means the job ran; the `verdict` says whether to trust the pose**: `ok` use it, `check` look at "
    "the overlays first, `failed` do not use it (`result.verdict` = `result.metrics.confidence.verdict`, with "
    "`reasons` in plain words). Errors are `application/problem+json` (RFC 9457)."
)


def create_app(settings: ServiceSettings, *, executor: Executor | None = None, start_background: bool = True) -> FastAPI:
    holder: dict[str, ServiceContext | None] = {"ctx": None}
    metrics = make_metrics(lambda: holder["ctx"])
    lifespan = make_lifespan(settings, metrics, holder, executor=executor, make_executor=make_executor,
                             start_background=start_background)
    app = FastAPI(
        title="dsareg registration service",
        version=__version__,  # pyproject.toml's version (service/__init__.py)
        description=DESCRIPTION,
        lifespan=lifespan,
        responses=problem_responses(500),
        docs_url=None,  # served offline by docs_offline.install_docs
        redoc_url=None,
        generate_unique_id_function=operation_id,
    )
    app.add_middleware(BodyLimitMiddleware, limit=settings.limits.max_upload_bytes)
    app.add_middleware(BodyDeadlineMiddleware, idle_seconds=settings.server.http_body_idle_timeout_seconds)
    app.add_middleware(MetricsMiddleware, histogram=metrics.http_latency, routes_getter=lambda: app.router.routes)
    install_handlers(app)
    mount(app, registrations.router, events.router, tracking.router, review.router, artifacts.router, hemodynamics.router, operations.router, ui.router)
    install_docs(app)
    install_openapi(app, settings)
    return app


def http_protocol(settings: ServiceSettings) -> type:
    """The uvicorn HTTP protocol to serve the app with: h11's, its own 400s (a malformed Content-Length,
    request line or header, answered before the app runs) as problem+json (:mod:`service.api.httpfaults`),
    a request head late past ``http_header_timeout_seconds`` closed (:mod:`service.api.httpdeadlines`)."""
    return with_header_deadline(problem_http_protocol(), HttpDeadlines.of(settings).header_timeout_s)


def uvicorn_options(settings: ServiceSettings) -> dict:
    """The connection bound of ``dsareg serve`` (``uvicorn.run`` keyword arguments)."""
    return HttpDeadlines.of(settings).uvicorn_options()


# ---- the DICOM node in its own process (`dsareg dicom-listener`) ---------------------------------


def _listener_context(settings: ServiceSettings) -> ServiceContext:
    """What the listener's submissions need (no HTTP): store, blobs, a validator, the executor."""
    from prometheus_client import CollectorRegistry, Counter

    from .api.intake.validation import ValidatorPool
    from .jobs.executor import NoExecutor
    from .storage.dbblobs import make_blob_store
    from .storage.store import SqlJobStore

    settings.storage.data_dir.mkdir(parents=True, exist_ok=True)
    store = SqlJobStore(settings.effective_database_url)
    validator = ValidatorPool(settings.limits.validation_processes, settings.limits.validation_timeout_seconds,
                              settings.limits.validation_memory_mb, threads=settings.jobs.threads_per_worker)
    validator.start()
    # embedded workers belong to `dsareg serve` (they poll the job table); Celery gets a message
    executor = make_executor(settings, store) if settings.jobs.executor == "celery" else NoExecutor()
    registry = CollectorRegistry()
    return ServiceContext(settings=settings, store=store, blobs=make_blob_store(settings, store.engine),
                          validator=validator, executor=executor, registry=registry,
                          uploads=Counter("dsareg_dimse_upload_bytes", "unused", registry=registry))


def run_dicom_listener(settings: ServiceSettings) -> int:
    """``dsareg dicom-listener``: the DICOM node alone, until SIGTERM / SIGINT."""
    import asyncio
    import logging
    import signal
    import threading
    import time

    from .api.intake.dimse import DimseIntake
    from .pacs.dimse.listener import DicomListener

    if not settings.dimse.dicom_port:
        logging.getLogger("dsareg.dimse").error("set DSAREG_DICOM_PORT (the listener's TCP port)")
        return 2
    ctx = _listener_context(settings)
    loop = asyncio.new_event_loop()
    loop_thread = threading.Thread(target=loop.run_forever, name="dimse-submit-loop", daemon=True)
    loop_thread.start()
    listener = DicomListener(settings, ctx.store, ctx.blobs, DimseIntake(ctx), loop)
    stopping = threading.Event()
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: stopping.set())
    try:
        deadline = time.monotonic() + settings.limits.validation_timeout_seconds
        while not ctx.validator.ready() and time.monotonic() < deadline:
            time.sleep(0.1)
        ctx.executor.start()
        listener.start()
        print(f"dsareg dicom-listener: {settings.dimse.dicom_ae_title} on {settings.dimse.dicom_host}:{listener.port}", flush=True)
        stopping.wait()
    finally:
        listener.stop()
        loop.call_soon_threadsafe(loop.stop)
        loop_thread.join(5)
        ctx.executor.stop()
        ctx.validator.stop()
        ctx.store.dispose()
    return 0
