"""RFC 9457 problem details: the one error format of the API.

Handlers raise :class:`Problem`; the exception handlers in :mod:`service.api.handlers` turn it
(and FastAPI's validation errors, Starlette's HTTP errors and anything unexpected)
into ``application/problem+json``. Nothing internal (tracebacks, paths, SQL) is ever
put into a problem body.
"""

from __future__ import annotations

from typing import Any

from pydantic import BaseModel, ConfigDict, Field

PROBLEM_MEDIA_TYPE = "application/problem+json"
TYPE_BASE = "https://dsareg.dev/problems/"

TITLES = {
    400: "Bad request",
    401: "Authentication required",
    403: "Forbidden",
    404: "Not found",
    405: "Method not allowed",
    406: "Not acceptable",
    408: "Request timeout",
    409: "Conflict",
    413: "Request body too large",
    415: "Unsupported media type",
    422: "Unprocessable input",
    429: "Too many requests",
    500: "Internal server error",
    503: "Service unavailable",
    507: "Insufficient storage",
}


class ProblemDetails(BaseModel):
    """RFC 9457 problem details, plus ``field`` and ``accepted`` for input errors."""

    model_config = ConfigDict(
        extra="allow",
        json_schema_extra={
            "examples": [
                {
                    "type": TYPE_BASE + "invalid-input",
                    "title": "Unprocessable input",
                    "status": 422,
                    "detail": "options.starts: Input should be greater than or equal to 1",
                    "instance": "/v1/registrations",
                    "field": "options.starts",
                    "accepted": "a JSON object with fields configuration, starts, ...",
                }
            ]
        },
    )

    type: str = Field(TYPE_BASE + "error", description="URI identifying the problem type.")
    title: str = Field(description="Short summary of the problem type.")
    status: int = Field(description="HTTP status code.")
    detail: str | None = Field(None, description="What went wrong in this occurrence and how to fix it.")
    instance: str | None = Field(None, description="The request path (or job) concerned.")
    field: str | None = Field(None, description="The input or field at fault, for input errors.")
    accepted: str | None = Field(None, description="What would have been accepted.")


class Problem(Exception):
    """An error response. ``kind`` becomes the last part of the ``type`` URI."""

    def __init__(
        self,
        status: int,
        detail: str,
        *,
        kind: str | None = None,
        title: str | None = None,
        field: str | None = None,
        accepted: str | None = None,
        headers: dict[str, str] | None = None,
        extra: dict[str, Any] | None = None,
    ):
        super().__init__(detail)
        self.status = status
        self.detail = detail
        self.kind = kind or _default_kind(status)
        self.title = title or TITLES.get(status, "Error")
        self.field = field
        self.accepted = accepted
        self.headers = headers or {}
        self.extra = extra or {}

    def body(self, instance: str | None) -> dict[str, Any]:
        return problem_body(
            self.status, self.detail, kind=self.kind, title=self.title, instance=instance,
            field=self.field, accepted=self.accepted, **self.extra,
        )


def _default_kind(status: int) -> str:
    return {
        400: "bad-request", 401: "unauthorized", 403: "forbidden", 404: "not-found", 405: "method-not-allowed",
        408: "request-timeout", 409: "conflict", 413: "payload-too-large", 415: "unsupported-media-type", 422: "invalid-input",
        429: "too-many-requests", 500: "internal-error", 503: "unavailable", 507: "insufficient-storage",
    }.get(status, "error")


def problem_body(
    status: int, detail: str | None, *, kind: str | None = None, title: str | None = None,
    instance: str | None = None, field: str | None = None, accepted: str | None = None, **extra: Any,
) -> dict[str, Any]:
    body: dict[str, Any] = {
        "type": TYPE_BASE + (kind or _default_kind(status)),
        "title": title or TITLES.get(status, "Error"),
        "status": status,
        "detail": detail,
        "instance": instance,
    }
    if field is not None:
        body["field"] = field
    if accepted is not None:
        body["accepted"] = accepted
    body.update(extra)
    return body


def problem_responses(*codes: int) -> dict[int | str, dict[str, Any]]:
    """OpenAPI ``responses`` entries for error codes (problem+json, with an example each)."""
    examples = {
        400: "The request is malformed: 'geometry' is not valid JSON (Expecting value at line 1).",
        401: "Send 'Authorization: Bearer <API key>'.",
        403: "Metrics are not public on this server and no API keys are configured.",
        404: "No registration job with id '0b5a…'.",
        408: "No request body bytes arrived for 30 s (DSAREG_HTTP_BODY_IDLE_TIMEOUT_SECONDS).",
        409: "Idempotency-Key 'k1' was already used with a different request body.",
        413: "The request body exceeds the upload limit of 512 MiB (536870912 bytes); send smaller files, or raise "
             "the server's setting DSAREG_MAX_UPLOAD_BYTES.",
        415: "Send multipart/form-data with the files mesh (or volume), ap and lat.",
        422: "ap: cannot read the image (accepted: PNG, JPEG, TIFF, DICOM)",
        429: "This API key already has 200 queued jobs; retry later.",
        500: "An internal error occurred; it has been logged.",
        503: "The job queue is full (1000 queued); retry later.",
        507: "The server's data disk is nearly full (200 MiB free, 256 MiB are kept free); retry later.",
    }
    out: dict[int | str, dict[str, Any]] = {}
    for code in codes:
        example = problem_body(code, examples.get(code), instance="/v1/registrations")
        out[code] = {
            "description": TITLES.get(code, "Error"),
            "content": {PROBLEM_MEDIA_TYPE: {"schema": {"$ref": "#/components/schemas/ProblemDetails"}, "example": example}},
        }
        if code in (429, 503, 507):
            out[code]["headers"] = {"Retry-After": {"description": "Seconds to wait.", "schema": {"type": "integer"}}}
        if code == 401:
            out[code]["headers"] = {"WWW-Authenticate": {"description": "Bearer", "schema": {"type": "string"}}}
    return out
