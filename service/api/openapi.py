"""Patches to the generated OpenAPI document."""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter, FastAPI

from ..problems import ProblemDetails, problem_responses
from .schemas.payloads import document as document_payloads
from ..settings import ServiceSettings


def operation_id(route: Any) -> str:
    """operationId = the handler's name (``submit``, ``get_job``, ``list_jobs``...): what generated clients call."""
    return route.name


def resource_router(tag: str) -> APIRouter:
    """The router of one resource, documented as the app's own routes are (operation ids, 500 response).

    :func:`mount` adds its routes to the app flat, as ``@app.get`` would: code that walks
    ``app.router.routes`` (the 405 ``Allow`` header, the metrics' route templates) sees every route
    (FastAPI's ``include_router`` adds a lazily resolved branch instead).
    """
    return APIRouter(tags=[tag], responses=problem_responses(500), generate_unique_id_function=operation_id)


def mount(app: FastAPI, *routers: APIRouter) -> None:
    for router in routers:
        app.router.routes.extend(router.routes)


def _operations(schema: dict[str, Any]):
    for operations in schema.get("paths", {}).values():
        yield from operations.values()


def patch_schema(schema: dict[str, Any], settings: ServiceSettings) -> dict[str, Any]:
    document_payloads(schema)  # options, geometry and result schemas; the multipart parts
    schemas = schema.setdefault("components", {}).setdefault("schemas", {})
    schemas["ProblemDetails"] = ProblemDetails.model_json_schema(ref_template="#/components/schemas/{model}")
    # FastAPI documents its own 422 body; ours is problem+json like every other error
    problem_422 = problem_responses(422)[422]
    for operation in _operations(schema):
        responses = operation.get("responses", {})
        if "422" in responses:
            responses["422"] = problem_422
    for name in ("HTTPValidationError", "ValidationError"):
        schemas.pop(name, None)
    if not settings.auth.auth_enabled:  # no keys: nothing to authenticate with, so no scheme and no lock in /docs
        for operation in _operations(schema):
            operation.pop("security", None)
        schema.get("components", {}).pop("securitySchemes", None)
    return schema


def install_openapi(app: FastAPI, settings: ServiceSettings) -> None:
    original_openapi = app.openapi

    def openapi() -> dict[str, Any]:
        if app.openapi_schema:
            return app.openapi_schema
        app.openapi_schema = patch_schema(original_openapi(), settings)
        return app.openapi_schema

    app.openapi = openapi  # type: ignore[method-assign]
