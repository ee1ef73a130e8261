"""The 413 tells the client the limit in MiB and the server setting that raises it (service/api/middleware.py)."""

from __future__ import annotations

import asyncio
import json

from service.api.middleware import BodyLimitMiddleware


async def _never_called(scope, receive, send):  # pragma: no cover - the limit answers first
    raise AssertionError("the app must not see a body over the limit")


def _answer(declared: int, limit: int) -> tuple[int, dict]:
    sent: list[dict] = []

    async def send(message):
        sent.append(message)

    async def receive():
        return {"type": "http.request", "body": b"", "more_body": False}

    scope = {"type": "http", "path": "/v1/registrations", "headers": [(b"content-length", str(declared).encode())]}
    asyncio.run(BodyLimitMiddleware(_never_called, limit)(scope, receive, send))
    return sent[0]["status"], json.loads(sent[1]["body"])


def test_a_too_large_body_names_the_limit_in_mib_and_the_setting():
    status, body = _answer(600 << 20, 512 << 20)
    assert status == 413
    assert "512 MiB" in body["detail"] and "DSAREG_MAX_UPLOAD_BYTES" in body["detail"]
