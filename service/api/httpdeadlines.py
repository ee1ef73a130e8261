"""How long one HTTP client may hold the API, and how many may: header and body read deadlines, a connection bound.

uvicorn reads request heads and bodies with no deadline of its own (its keep-alive timeout stops at the
first byte), so a client that sends a byte now and then holds its connection, and a stalled upload holds
its request, for as long as it likes. Here:

* **head** (:func:`with_header_deadline`, in the h11 protocol): the request line and headers must be
  complete within ``header_timeout_s`` of the connection (or of the previous response); otherwise the
  API answers ``408`` and closes the connection;
* **body** (:class:`BodyDeadlineMiddleware`, ASGI): no body bytes for ``body_idle_timeout_s`` while the
  body is incomplete → ``408`` problem+json, connection closed; a body that keeps arriving is bounded by
  the upload limit (413), not by time;
* **connections** (uvicorn's ``limit_concurrency``): past ``max_connections`` open connections a
  request is answered ``503`` at once instead of queuing.
"""

from __future__ import annotations

import asyncio
import json
from dataclasses import dataclass
from typing import Any

from ..problems import PROBLEM_MEDIA_TYPE, problem_body
from .middleware import ResponseTracker, caused_by

TIMEOUT_408 = b"HTTP/1.1 408 Request Timeout\r\nContent-Length: 0\r\nConnection: close\r\n\r\n"


@dataclass(frozen=True)
class HttpDeadlines:
    header_timeout_s: float
    body_idle_timeout_s: float
    max_connections: int

    @classmethod
    def of(cls, settings: Any) -> HttpDeadlines:
        server = settings.server
        return cls(server.http_header_timeout_seconds, server.http_body_idle_timeout_seconds,
                   server.http_max_connections)

    def uvicorn_options(self) -> dict[str, Any]:
        """Keyword arguments of ``uvicorn.run`` (the protocol is given separately)."""
        return {"limit_concurrency": self.max_connections}


def with_header_deadline(protocol: type, seconds: float) -> type:
    """``protocol`` (uvicorn's h11 protocol or a subclass) closing connections whose request head is late."""
    import h11

    class HeaderDeadlineProtocol(protocol):  # type: ignore[misc, valid-type]
        _head_timer: asyncio.TimerHandle | None = None

        def connection_made(self, transport: Any) -> None:
            super().connection_made(transport)
            self._arm_head_deadline()

        def connection_lost(self, exc: Exception | None) -> None:
            self._disarm_head_deadline()
            super().connection_lost(exc)

        def handle_events(self) -> None:
            super().handle_events()
            if self.conn.their_state is not h11.IDLE:  # the head is in (a body, or the end, follows)
                self._disarm_head_deadline()

        def on_response_complete(self) -> None:
            super().on_response_complete()
            if not self.transport.is_closing():
                self._arm_head_deadline()  # the next request's head, on a kept-alive connection

        def _arm_head_deadline(self) -> None:
            self._disarm_head_deadline()
            self._head_timer = self.loop.call_later(seconds, self._head_too_late)

        def _disarm_head_deadline(self) -> None:
            if self._head_timer is not None:
                self._head_timer.cancel()
                self._head_timer = None

        def _head_too_late(self) -> None:
            self._head_timer = None
            if self.conn.their_state is h11.IDLE and not self.transport.is_closing():
                if self.conn.our_state is h11.IDLE:  # nothing of an answer sent yet
                    self.transport.write(TIMEOUT_408)  # not through h11: it answers only a whole request
                self.transport.close()

    return HeaderDeadlineProtocol


class BodyTimeout(Exception):
    pass


class BodyDeadlineMiddleware:
    """408 when a request body stops arriving for ``idle_seconds`` (only while the body is incomplete)."""

    def __init__(self, app: Any, idle_seconds: float):
        self.app, self.idle_seconds = app, idle_seconds

    async def __call__(self, scope: dict, receive: Any, send: Any) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        body_done = False
        tracked = ResponseTracker(send)

        async def deadline_receive() -> dict:
            nonlocal body_done
            if body_done:
                return await receive()
            try:
                message = await asyncio.wait_for(receive(), self.idle_seconds)
            except TimeoutError:
                raise BodyTimeout() from None
            if message["type"] != "http.request" or not message.get("more_body", False):
                body_done = True
            return message

        try:
            await self.app(scope, deadline_receive, tracked)
        except Exception as exc:
            if not caused_by(exc, BodyTimeout):
                raise
            if not tracked.started:
                await self._send_408(send, scope)

    async def _send_408(self, send: Any, scope: dict) -> None:
        detail = (f"no request body bytes arrived for {self.idle_seconds:g} s (DSAREG_HTTP_BODY_IDLE_TIMEOUT_SECONDS); "
                  "send the body without pauses")
        body = json.dumps(problem_body(408, detail, instance=scope.get("path", ""))).encode()
        await send({"type": "http.response.start", "status": 408,
                    "headers": [(b"content-type", PROBLEM_MEDIA_TYPE.encode()),
                                (b"content-length", str(len(body)).encode()), (b"connection", b"close")]})
        await send({"type": "http.response.body", "body": body})

