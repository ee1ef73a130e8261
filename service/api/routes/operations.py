"""Operations: liveness, readiness, Prometheus metrics."""

from __future__ import annotations

from pathlib import Path

from fastapi import Depends, Request
from fastapi.responses import JSONResponse, Response
from fastapi.security import HTTPAuthorizationCredentials
from prometheus_client import CONTENT_TYPE_LATEST, generate_latest

from ...problems import Problem, problem_responses
from ..deps import Ctx, bearer, principal
from ..openapi import resource_router
from ..schemas.jobs import Health

router = resource_router("operations")


@router.get("/healthz", response_model=Health, summary="Liveness")
def healthz() -> Health:
    return Health(status="ok")


@router.get("/readyz", response_model=Health, summary="Readiness: store writable, a worker warmed up and idle-able",
            description="200 when the job store is writable, the input validator is up and at least one worker "
                        "has finished its warm-up (on a fresh install the first warm-up compiles the numba kernels: "
                        "minutes on 2 cores; `dsareg warmup` does it ahead). While workers warm up: 503 with "
                        "`checks.warming` and `checks.workers_ready` / `checks.workers_alive`.",
            responses={503: {"description": "Not ready", "model": Health}})
def readyz(ctx: Ctx) -> Response:
    store_ok = ctx.jobs.ping()
    # workers are counted in the database (Celery's alive, everyone's ready): not asked again when it just
    # failed (one deadline, not three)
    alive = ctx.executor.alive_workers() if store_ok or ctx.settings.jobs.executor == "embedded" else 0
    ready_workers = ctx.executor.ready_workers() if alive and store_ok else 0
    checks = {
        "store_writable": store_ok,
        "workers_alive": alive,
        "workers_ready": ready_workers,
        "validator_alive": ctx.validator.alive() if ctx.validator else False,
        "validator_ready": ctx.validator.ready() if ctx.validator else False,
        "validator_spare_ready": ctx.validator.spare_ready() if ctx.validator else False,
    }
    if alive and not ready_workers:
        checks["warming"] = "compiling kernels: workers are warming up (minutes on a fresh install, seconds after)"
    data_ok = Path(ctx.settings.storage.data_dir).is_dir()
    checks["data_dir"] = data_ok
    ready = (checks["store_writable"] and ready_workers > 0 and data_ok
             and (ctx.validator is None or checks["validator_ready"]))
    body = Health(status="ok" if ready else "unavailable", checks=checks)
    return JSONResponse(body.model_dump(), status_code=200 if ready else 503,
                        headers=None if ready else {"Retry-After": "5"})


@router.get("/metrics", summary="Prometheus metrics (service-wide aggregates)", response_class=Response,
            description="Public when `DSAREG_METRICS_PUBLIC` is true, or when it is unset and no API keys are "
                        "configured; otherwise it needs `Authorization: Bearer <API key>` (any valid key). Only "
                        "aggregates: no key, job id or request path appears in it.",
            responses={200: {"content": {"text/plain": {"schema": {"type": "string"}}}, "description": "Prometheus text"},
                       **problem_responses(401, 403)})
def metrics(ctx: Ctx, request: Request, credentials: HTTPAuthorizationCredentials | None = Depends(bearer)) -> Response:  # noqa: B008
    if not ctx.settings.auth.metrics_open:
        if not ctx.settings.auth.auth_enabled:
            raise Problem(403, "metrics are not public on this server (DSAREG_METRICS_PUBLIC=false) and no API keys "
                               "are configured", field="DSAREG_METRICS_PUBLIC")
        principal(request, credentials)  # 401 without a valid key
    return Response(generate_latest(ctx.registry), media_type=CONTENT_TYPE_LATEST)
