"""Pure ASGI middleware: upload limit enforced while streaming, and request metrics/logs."""

from __future__ import annotations

import json
import logging
import time
from typing import Any

from ..problems import PROBLEM_MEDIA_TYPE, problem_body

log = logging.getLogger("dsareg.service.http")


class BodyTooLarge(Exception):
    pass


async def _send_problem(send: Any, status: int, detail: str, instance: str, headers: list | None = None) -> None:
    body = json.dumps(problem_body(status, detail, instance=instance)).encode()
    await send({
        "type": "http.response.start", "status": status,
        "headers": [(b"content-type", PROBLEM_MEDIA_TYPE.encode()), (b"content-length", str(len(body)).encode()),
                    (b"connection", b"close"), *(headers or [])],
    })
    await send({"type": "http.response.body", "body": body})


def upload_limit_detail(limit: int) -> str:
    """The 413's detail: the limit in MiB and the setting that raises it."""
    return (f"the request body exceeds the upload limit of {limit / 2**20:.4g} MiB ({limit} bytes); send smaller "
            "files, or raise the server's setting DSAREG_MAX_UPLOAD_BYTES")


class BodyLimitMiddleware:
    """413 as soon as more than ``limit`` body bytes arrive (chunked or not, whatever
    Content-Length claims); a too-large Content-Length is refused before reading."""

    def __init__(self, app: Any, limit: int):
        self.app = app
        self.limit = limit

    async def __call__(self, scope: dict, receive: Any, send: Any) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        detail = upload_limit_detail(self.limit)
        for name, value in scope.get("headers", []):
            if name == b"content-length":
                try:
                    declared = int(value)
                except ValueError:
                    declared = 0
                if declared > self.limit:
                    await _send_problem(send, 413, detail, scope.get("path", ""))
                    return
        received = 0
        tracked = ResponseTracker(send)

        async def limited_receive() -> dict:
            nonlocal received
            message = await receive()
            if message["type"] == "http.request":
                received += len(message.get("body", b""))
                if received > self.limit:
                    raise BodyTooLarge()
            return message

        try:
            await self.app(scope, limited_receive, tracked)
        except BodyTooLarge:
            if not tracked.started:
                await _send_problem(send, 413, detail, scope.get("path", ""))
        except Exception as exc:  # the limit may surface wrapped by a form parser
            if caused_by(exc, BodyTooLarge) and not tracked.started:
                await _send_problem(send, 413, detail, scope.get("path", ""))
            else:
                raise


class ResponseTracker:
    """An ASGI ``send`` that remembers whether the response head went out (after it no error answer can be sent)."""

    def __init__(self, send: Any) -> None:
        self._send = send
        self.started = False

    async def __call__(self, message: dict) -> None:
        if message["type"] == "http.response.start":
            self.started = True
        await self._send(message)


def caused_by(exc: BaseException, kind: type) -> bool:
    """Whether ``exc`` is ``kind`` or was raised by one (causes, contexts, exception groups; 10 links at most)."""
    seen = 0
    current: BaseException | None = exc
    while current is not None and seen < 10:
        if isinstance(current, kind):
            return True
        if isinstance(current, BaseExceptionGroup) and any(caused_by(e, kind) for e in current.exceptions):
            return True
        current = current.__cause__ or current.__context__
        seen += 1
    return False


class MetricsMiddleware:
    """Observes latency per route template (never per raw path) and logs one line per request."""

    def __init__(self, app: Any, histogram: Any, routes_getter: Any = None):
        self.app = app
        self.histogram = histogram
        self.routes_getter = routes_getter

    def _template(self, scope: dict) -> str:
        route = scope.get("route")
        if route is not None:
            return getattr(route, "path", "unmatched")
        if self.routes_getter is None:
            return "unmatched"
        from starlette.routing import Match

        partial = None
        for candidate in self.routes_getter():
            match, _ = candidate.matches(scope)
            if match == Match.FULL:
                return getattr(candidate, "path", "unmatched")
            if match == Match.PARTIAL and partial is None:
                partial = getattr(candidate, "path", None)
        return partial or "unmatched"

    async def __call__(self, scope: dict, receive: Any, send: Any) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        started = time.perf_counter()
        status = 500

        async def capture(message: dict) -> None:
            nonlocal status
            if message["type"] == "http.response.start":
                status = message["status"]
            await send(message)

        try:
            await self.app(scope, receive, capture)
        finally:
            elapsed = time.perf_counter() - started
            template = self._template(scope)
            self.histogram.labels(scope.get("method", ""), template, str(status)).observe(elapsed)
            log.info("%s %s %s %.1f ms", scope.get("method", ""), template, status, elapsed * 1000)
