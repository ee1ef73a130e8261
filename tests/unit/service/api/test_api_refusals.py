"""Intake refusals become the problem+json answers the API always gave (service/api/handlers.py).

The expected bodies and headers are written out as the API answered them before submission moved out of
the HTTP layer (status, ``type``, ``Retry-After``, ``field``, ``job_id``): the move must not change them."""

from __future__ import annotations

import asyncio
import json

import pytest
from starlette.requests import Request

from service.api.handlers import on_refusal
from service.intake.refusals import IdempotencyConflict, InvalidInput, Overloaded, QuotaExceeded, Refusal

BASE = "https://dsareg.dev/problems/"


def _answer(exc: Refusal) -> tuple[int, dict, dict]:
    request = Request({"type": "http", "method": "POST", "path": "/v1/registrations", "headers": [],
                       "query_string": b""})
    response = asyncio.run(on_refusal(request, exc))
    return response.status_code, json.loads(response.body), dict(response.headers)


@pytest.mark.parametrize("refusal, status, kind, title, retry_after", [
    (InvalidInput("the file is empty", field="ap"), 422, "invalid-input", "Unprocessable input", None),
    (InvalidInput("too costly", field="options", kind="job-too-expensive"), 422, "job-too-expensive",
     "Unprocessable input", None),
    (Overloaded("the job queue is full (3 queued); retry later", kind="queue-full", retry_after_s=30), 503,
     "queue-full", "Service unavailable", "30"),
    (Overloaded("input validation is temporarily unavailable", kind="validator-unavailable", retry_after_s=5), 503,
     "validator-unavailable", "Service unavailable", "5"),
    (QuotaExceeded("this API key already has 2 queued jobs; retry later", retry_after_s=30), 429,
     "too-many-requests", "Too many requests", "30"),
])
def test_each_refusal_has_its_status_type_and_retry_after(refusal, status, kind, title, retry_after):
    code, body, headers = _answer(refusal)
    assert code == status and headers["content-type"] == "application/problem+json"
    assert body["type"] == BASE + kind and body["title"] == title and body["status"] == status
    assert body["detail"] == refusal.detail and body["instance"] == "/v1/registrations"
    assert headers.get("retry-after") == retry_after
    assert body.get("field") == refusal.field


def test_an_invalid_input_names_the_field_and_what_is_accepted():
    code, body, _ = _answer(InvalidInput("is not UTF-8 text", field="options", accepted="UTF-8 JSON text"))
    assert (code, body) == (422, {"type": BASE + "invalid-input", "title": "Unprocessable input", "status": 422,
                                  "detail": "is not UTF-8 text", "instance": "/v1/registrations",
                                  "field": "options", "accepted": "UTF-8 JSON text"})


def test_an_idempotency_conflict_is_a_409_naming_the_job():
    code, body, headers = _answer(IdempotencyConflict("used before", field="Idempotency-Key", job_id="j1"))
    assert code == 409 and "retry-after" not in headers
    assert body == {"type": BASE + "idempotency-conflict", "title": "Conflict", "status": 409, "detail": "used before",
                    "instance": "/v1/registrations", "field": "Idempotency-Key", "job_id": "j1"}
