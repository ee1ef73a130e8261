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
from .api.secure_headers import SecureHeadersMiddleware
from .api.auth_throttle import FailureThrottle
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
    app.add_middleware(SecureHeadersMiddleware)  # outermost: no-store + nosniff on every answer, 413s included
    app.state.auth_throttle = FailureThrottle()  # wrong API keys per client address: 429 after 10 in 60 s
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


class TlsOptionError(ValueError):
    """``--ssl-certfile`` / ``--ssl-keyfile`` that cannot serve HTTPS (one line at start, exit 2)."""

    def cli_explanation(self) -> tuple[bool, str]:
        return True, str(self)


def tls_options(certfile: str | None, keyfile: str | None) -> dict:
    """uvicorn's own TLS for ``dsareg serve --ssl-certfile PEM --ssl-keyfile PEM`` (``uvicorn.run`` keyword
    arguments; empty without them): both or neither, loaded once here so a wrong file stops the start with one
    line instead of failing every handshake (docs/deployment/security.md)."""
    if not certfile and not keyfile:
        return {}
    if not (certfile and keyfile):
        raise TlsOptionError("--ssl-certfile and --ssl-keyfile go together (the certificate and its private key)")
    import ssl

    try:
        ssl.create_default_context(ssl.Purpose.CLIENT_AUTH).load_cert_chain(certfile, keyfile)
    except (OSError, ssl.SSLError) as exc:
        raise TlsOptionError(f"cannot serve HTTPS with certificate {certfile} and key {keyfile}: {exc}") from None
    return {"ssl_certfile": certfile, "ssl_keyfile": keyfile}
