"""Exception handlers: every error is ``application/problem+json`` (RFC 9457)."""

from __future__ import annotations

import logging
from typing import Any

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.requests import ClientDisconnect

from ..engine_adapter import engine
from ..intake.pacs_access import AccessDenied
from ..intake.refusals import IdempotencyConflict, InvalidInput, Overloaded, QuotaExceeded, Refusal
from ..problems import PROBLEM_MEDIA_TYPE, Problem, problem_body
from ..storage.diskspace import RETRY_AFTER_SECONDS as DISK_RETRY_AFTER
from ..storage.diskspace import DiskFull, is_disk_full
from ..storage.store import store_outage_errors
from .httpfaults import allowed_methods

log = logging.getLogger("dsareg.service")

STORE_RETRY_AFTER = "5"
REFUSAL_STATUS: dict[type[Refusal], int] = {InvalidInput: 422, IdempotencyConflict: 409, QuotaExceeded: 429,
                                            Overloaded: 503, AccessDenied: 403}
"""The HTTP status of each intake refusal (:mod:`service.intake.refusals`); the most specific class wins."""


def problem_response(status: int, body: dict[str, Any], headers: dict[str, str] | None = None) -> JSONResponse:
    return JSONResponse(body, status_code=status, media_type=PROBLEM_MEDIA_TYPE, headers=headers)


def route_template(request: Request) -> str:
    route = request.scope.get("route")
    return getattr(route, "path", "unmatched")


async def on_problem(request: Request, exc: Problem) -> JSONResponse:
    return problem_response(exc.status, exc.body(request.url.path), exc.headers)


def refusal_problem(exc: Refusal) -> Problem:
    """The problem an intake refusal is answered with: its status by class, a Retry-After when it says when."""
    status = next((REFUSAL_STATUS[cls] for cls in type(exc).__mro__ if cls in REFUSAL_STATUS), 422)
    headers = {"Retry-After": str(exc.retry_after_s)} if isinstance(exc, Overloaded) else None
    return Problem(status, exc.detail, kind=exc.kind, field=exc.field, accepted=exc.accepted, headers=headers,
                   extra=exc.extra)


async def on_refusal(request: Request, exc: Refusal) -> JSONResponse:
    return await on_problem(request, refusal_problem(exc))


async def on_input_error(request: Request, exc: Exception) -> JSONResponse:
    """The engine refused an input (``DsaregInputError``: message, field, accepted): 422, the one mapping."""
    problem = Problem(422, exc.message, field=exc.field, accepted=exc.accepted)  # type: ignore[attr-defined]
    return await on_problem(request, problem)


async def on_http(request: Request, exc: StarletteHTTPException) -> JSONResponse:
    detail = exc.detail if isinstance(exc.detail, str) else None
    if exc.status_code == 404 and detail in (None, "Not Found"):
        detail = f"no such endpoint: {request.method} {request.url.path[:200]}; see /docs"
    headers = dict(exc.headers or {})
    if exc.status_code == 405:
        detail = f"{request.method} is not allowed on {request.url.path[:200]}; see /docs"
        headers["Allow"] = allowed_methods(request.app.router.routes, request.scope) or headers.get("Allow", "")
    return problem_response(exc.status_code, problem_body(exc.status_code, detail, instance=request.url.path),
                            headers)


async def on_validation(request: Request, exc: RequestValidationError) -> JSONResponse:
    errors = exc.errors()
    first = errors[0] if errors else {"loc": (), "msg": "invalid request"}
    loc = [str(p) for p in first.get("loc", ())]
    field_name = ".".join(loc[1:]) if len(loc) > 1 else ".".join(loc) or None
    where = loc[0] if loc else "request"
    detail = f"{where} parameter '{field_name}': {first.get('msg')}" if field_name else str(first.get("msg"))
    return problem_response(422, problem_body(422, detail, kind="invalid-parameter", instance=request.url.path,
                                              field=field_name))


async def on_disconnect(request: Request, exc: ClientDisconnect) -> JSONResponse:
    # the client went away mid-request (often mid-upload): nothing to answer, nothing broken here
    log.info("client disconnected during %s %s", request.method, route_template(request))
    return problem_response(400, problem_body(400, "the client disconnected before the request was complete",
                                              kind="client-disconnected", instance=request.url.path))


async def on_store_unavailable(request: Request, exc: Exception) -> JSONResponse:
    """The job database is down or busy: a temporary condition (503 + Retry-After), not a bug (500)."""
    log.warning("job store unavailable on %s %s: %s", request.method, route_template(request), type(exc).__name__)
    return problem_response(503, problem_body(503, "the job database is temporarily unavailable; retry later",
                                              kind="store-unavailable", instance=request.url.path),
                            {"Retry-After": STORE_RETRY_AFTER})


async def on_disk_full(request: Request, exc: Exception) -> JSONResponse:
    """No room on the data disk (below ``min_free_bytes``, or ENOSPC mid-write): 507 + Retry-After."""
    log.warning("disk full on %s %s: %s", request.method, route_template(request), type(exc).__name__)
    detail = exc.detail if isinstance(exc, DiskFull) else "the server's data disk is full; retry later"
    return problem_response(507, problem_body(507, detail, kind="insufficient-storage", instance=request.url.path),
                            {"Retry-After": str(DISK_RETRY_AFTER)})


async def on_internal(request: Request, exc: Exception) -> JSONResponse:
    if is_disk_full(exc):  # ENOSPC raised by a write not wrapped as DiskFull: a known condition, not a bug
        return await on_disk_full(request, exc)
    log.error("internal error on %s %s: %s", request.method, route_template(request), type(exc).__name__,
              exc_info=exc)
    return problem_response(500, problem_body(500, "an internal error occurred; it has been logged",
                                              instance=request.url.path))


def install_handlers(app: FastAPI) -> None:
    app.add_exception_handler(Problem, on_problem)  # type: ignore[arg-type]
    app.add_exception_handler(engine.DsaregInputError, on_input_error)
    app.add_exception_handler(Refusal, on_refusal)  # type: ignore[arg-type]
    app.add_exception_handler(StarletteHTTPException, on_http)  # type: ignore[arg-type]
    app.add_exception_handler(RequestValidationError, on_validation)  # type: ignore[arg-type]
    app.add_exception_handler(ClientDisconnect, on_disconnect)  # type: ignore[arg-type]
    app.add_exception_handler(DiskFull, on_disk_full)
    for outage in store_outage_errors():
        app.add_exception_handler(outage, on_store_unavailable)
    app.add_exception_handler(Exception, on_internal)
