"""HTTP helpers: the complete ``Allow`` header of a 405, and protocol-level errors as problem+json.

A request h11 cannot parse (``Content-Length: -5`` or ``12abc``, two different Content-Length headers,
a malformed request line or header) never reaches the app: uvicorn answers it itself, by default with
``400 text/plain`` "Invalid HTTP request received.". :func:`problem_http_protocol` is uvicorn's h11
protocol answering those with a 400 ``application/problem+json`` naming the header where h11 says which
(``dsareg serve`` runs uvicorn with it).
"""

from __future__ import annotations

import json
import re
import sys
from typing import Any

PROTOCOL_HEADER = re.compile(r"content-length|transfer-encoding|host", re.IGNORECASE)


def allowed_methods(routes: Any, scope: dict) -> str:
    """Every method some route accepts on this path (Starlette's 405 names only the first route's)."""
    from starlette.routing import Match

    methods: set[str] = set()
    probe = {**scope, "method": "GET"}
    for route in routes:
        match, _ = route.matches({**probe, "type": "http"})
        if match != Match.NONE and getattr(route, "methods", None):
            methods |= set(route.methods)
    if "GET" in methods:
        methods.add("HEAD")
    return ", ".join(sorted(methods))


def protocol_problem(error: BaseException | None) -> dict[str, Any]:
    """The problem body for a request h11 refused with ``error`` (its message names what was wrong)."""
    from ..problems import problem_body

    reason = str(error or "").strip() or "malformed request"
    header = PROTOCOL_HEADER.search(reason)
    field = {"content-length": "Content-Length", "transfer-encoding": "Transfer-Encoding",
             "host": "Host"}.get(header.group().lower()) if header else None
    body = problem_body(400, f"the request is not valid HTTP/1.1: {reason[:200]}", kind="malformed-http",
                        field=field)
    if field == "Content-Length":
        body["accepted"] = "one Content-Length header with a non-negative decimal integer"
    return body


def problem_http_protocol() -> type:
    """uvicorn's h11 protocol class whose own 400 answers are problem+json (pass as ``uvicorn.run(http=...)``)."""
    import h11
    from uvicorn.protocols.http.h11_impl import H11Protocol

    from ..problems import PROBLEM_MEDIA_TYPE

    class ProblemH11Protocol(H11Protocol):
        def send_400_response(self, msg: str) -> None:
            # called from uvicorn's ``except h11.RemoteProtocolError`` block: the error is the one handled
            data = json.dumps(protocol_problem(sys.exc_info()[1])).encode()
            headers = [(b"content-type", PROBLEM_MEDIA_TYPE.encode()), (b"content-length", str(len(data)).encode()),
                       (b"connection", b"close")]
            for event in (h11.Response(status_code=400, headers=headers, reason=b"Bad Request"), h11.Data(data=data),
                          h11.EndOfMessage()):
                self.transport.write(self.conn.send(event))
            self.transport.close()

    return ProblemH11Protocol
