"""Headers a hospital's security review asks of every response: no PHI kept in a cache, no content sniffing.

:class:`SecureHeadersMiddleware` (pure ASGI, outermost) sets ``X-Content-Type-Options: nosniff`` on every
response and ``Cache-Control: no-store`` on every response that is not one of the :data:`PUBLIC_PATHS` or
under a :data:`PUBLIC_PREFIXES` folder: a job's status, result, list, audit and review JSON carry the patient's
name and ID, its overlays, ``reg.dcm``, ``model.json`` and hemodynamics files show the patient. The rule is
"everything but the PHI-free static files", so a route added later is covered without being named here; a
``Cache-Control`` a route set itself (the files once said ``private, max-age=86400``) is replaced.

:func:`docs_csp` gives the ``/docs`` and ``/redoc`` pages a Content-Security-Policy that lets the offline
Swagger UI and ReDoc (:mod:`service.api.docs_offline`) run and nothing else: scripts from this origin and the
page's own inline start-up script by its hash.
"""

from __future__ import annotations

import base64
import hashlib
import re
from typing import Any

from starlette.responses import Response

PUBLIC_PATHS = frozenset({"/ui", "/docs", "/docs/oauth2-redirect", "/redoc", "/openapi.json"})
PUBLIC_PREFIXES = ("/ui/", "/docs-static/")
"""The review page's and the API docs' static files: the same for everyone, no job data (they may be cached)."""
NO_STORE = b"no-store"
_INLINE_SCRIPT = re.compile(rb"<script>(.*?)</script>", re.S)
DOCS_POLICY = ("default-src 'self'; script-src 'self'{hashes}{eval}; style-src 'self' 'unsafe-inline'; "
               "img-src 'self' data: blob:; font-src 'self' data:; connect-src 'self'; worker-src 'self' blob:; "
               "object-src 'none'; base-uri 'none'; frame-ancestors 'none'; form-action 'self'")
"""Styles inline (both pages set styles from script), workers from blob: (ReDoc's search index)."""


def is_public(path: str) -> bool:
    """Whether ``path`` (without the root path) is a PHI-free static file that may be cached."""
    return path in PUBLIC_PATHS or path.startswith(PUBLIC_PREFIXES)


def _with(headers: list, name: bytes, value: bytes, *, replace: bool) -> list:
    present = any(key.lower() == name for key, _ in headers)
    if present and not replace:
        return headers
    return [(key, val) for key, val in headers if key.lower() != name] + [(name, value)]


class SecureHeadersMiddleware:
    """``nosniff`` on every HTTP response, ``no-store`` on every one but the :func:`is_public` files."""

    def __init__(self, app: Any) -> None:
        self.app = app

    async def __call__(self, scope: dict, receive: Any, send: Any) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        path, root = scope.get("path", ""), scope.get("root_path", "")
        public = is_public(path[len(root):] if root and path.startswith(root) else path)

        async def secured(message: dict) -> None:
            if message["type"] == "http.response.start":
                headers = _with(list(message.get("headers", [])), b"x-content-type-options", b"nosniff", replace=True)
                if not public:
                    headers = _with(headers, b"cache-control", NO_STORE, replace=True)
                message = {**message, "headers": headers}
            await send(message)

        await self.app(scope, receive, secured)


def docs_csp(response: Response, *, allow_eval: bool = False) -> Response:
    """``response`` (the ``/docs`` or ``/redoc`` page) with its CSP: its inline scripts allowed by hash only.

    ``allow_eval``: ReDoc compiles schema validators with ``new Function`` (its bundle), Swagger UI does not.
    """
    hashes = "".join(f" 'sha256-{base64.b64encode(hashlib.sha256(body).digest()).decode()}'"
                     for body in _INLINE_SCRIPT.findall(response.body))
    response.headers["Content-Security-Policy"] = DOCS_POLICY.format(
        hashes=hashes, eval=" 'unsafe-eval'" if allow_eval else "")
    response.headers["Referrer-Policy"] = "no-referrer"
    return response
