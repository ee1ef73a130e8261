"""Operations: liveness, readiness, Prometheus metrics."""

from __future__ import annotations

from pathlib import Path

from fastapi.responses import JSONResponse, Response
from prometheus_client import CONTENT_TYPE_LATEST, generate_latest

from ..schemas.jobs import Health
from ..deps import Ctx
from ..openapi import resource_router

router = resource_router("operations")


@router.get("/healthz", response_model=Health, summary="Liveness")
def healthz() -> Health:
    return Health(status="ok")


@router.get("/readyz", response_model=Health, summary="Readiness: store writable, a worker alive",
            responses={503: {"description": "Not ready", "model": Health}})
def readyz(ctx: Ctx) -> Response:
    checks = {
        "store_writable": ctx.store.ping(),
        "workers_alive": ctx.executor.alive_workers(),
        "validator_alive": ctx.validator.alive() if ctx.validator else False,
        "validator_ready": ctx.validator.ready() if ctx.validator else False,
    }
    data_ok = Path(ctx.settings.data_dir).is_dir()
    checks["data_dir"] = data_ok
    ready = (checks["store_writable"] and checks["workers_alive"] > 0 and data_ok
             and (ctx.validator is None or checks["validator_ready"]))
    body = Health(status="ok" if ready else "unavailable", checks=checks)
    return JSONResponse(body.model_dump(), status_code=200 if ready else 503,
                        headers=None if ready else {"Retry-After": "5"})


@router.get("/metrics", summary="Prometheus metrics", response_class=Response,
            responses={200: {"content": {"text/plain": {"schema": {"type": "string"}}}, "description": "Prometheus text"}})
def metrics(ctx: Ctx) -> Response:
    return Response(generate_latest(ctx.registry), media_type=CONTENT_TYPE_LATEST)
