"""``/ui/``: the review page, static files shipped in the package (:mod:`service.api.ui`).

The files hold no job data (the page fetches it from the API with the person's key), so they are
served without authentication, with a Content-Security-Policy that keeps the page to this origin.
"""

from __future__ import annotations

from importlib import resources

from fastapi import APIRouter, Request
from fastapi.responses import RedirectResponse, Response

from ...problems import Problem

router = APIRouter(include_in_schema=False)

JS = "text/javascript; charset=utf-8"
FILES = {"index.html": "text/html; charset=utf-8", "app.js": JS, "views2d.js": JS, "scene3d.js": JS,
         "app.css": "text/css; charset=utf-8"}
VENDOR = {"three.module.min.js": JS, "OrbitControls.js": JS}
"""three.js, vendored at a pinned version (static/vendor/three/README.md): only what the 3D scene imports."""
HEADERS = {
    "Content-Security-Policy": "default-src 'self'; img-src 'self' blob: data:; object-src 'none'; "
                               "base-uri 'none'; frame-ancestors 'none'; form-action 'none'",
    "X-Content-Type-Options": "nosniff",
    "Referrer-Policy": "no-referrer",
    "Cache-Control": "no-cache",
}


def _read(name: str, *folder: str) -> bytes:
    return resources.files("service.api.ui").joinpath("static", *folder, name).read_bytes()


@router.get("/ui")
def ui_root() -> Response:
    return RedirectResponse("/ui/", status_code=308)


KEY_FORM = b'<form id="key-form" class="key"'


def index_page(auth_enabled: bool) -> bytes:
    """``index.html``; without API keys configured its key box is sent hidden (there is no key to enter; app.js
    shows it again if a request is answered 401)."""
    page = _read("index.html")
    if auth_enabled:
        return page
    if KEY_FORM not in page:
        raise RuntimeError("service/api/ui/static/index.html lost its key form: index_page cannot hide it")
    return page.replace(KEY_FORM, KEY_FORM + b" hidden", 1)


@router.get("/ui/")
def ui_index(request: Request) -> Response:
    ctx = getattr(request.app.state, "ctx", None)
    auth_enabled = True if ctx is None else ctx.settings.auth.auth_enabled
    return Response(index_page(auth_enabled), media_type=FILES["index.html"], headers=HEADERS)


@router.get("/ui/{name}")
def ui_file(name: str) -> Response:
    if name not in FILES:
        raise Problem(404, f"no file '{name[:40]}' in the review page", accepted=", ".join(sorted(FILES)))
    return Response(_read(name), media_type=FILES[name], headers=HEADERS)


@router.get("/ui/vendor/three/{name}")
def ui_vendor_file(name: str) -> Response:
    if name not in VENDOR:
        raise Problem(404, f"no file '{name[:40]}' in the review page", accepted=", ".join(sorted(VENDOR)))
    return Response(_read(name, "vendor", "three"), media_type=VENDOR[name],
                    headers={**HEADERS, "Cache-Control": "public, max-age=86400"})
