"""``/docs`` (Swagger UI) and ``/redoc`` served from files installed with the package.

FastAPI's default pages load their scripts, styles, fonts and favicon from public CDNs, so
they stay blank on a hospital network without internet. The assets come from the
``fastapi-offline`` wheel (Swagger UI bundle and CSS, ReDoc standalone, a favicon) and are
mounted under ``/docs-static``; the pages name nothing outside the server (no Google Fonts,
no Swagger validator badge, ReDoc's CDN logo replaced by the local favicon). Without that package the service falls back to FastAPI's CDN
pages and logs a warning.
"""

from __future__ import annotations

import logging
from pathlib import Path

from fastapi import FastAPI, Request
from fastapi.openapi.docs import get_redoc_html, get_swagger_ui_html, get_swagger_ui_oauth2_redirect_html
from fastapi.responses import HTMLResponse, Response
from fastapi.staticfiles import StaticFiles

from .secure_headers import docs_csp

log = logging.getLogger("dsareg.service")

STATIC_URL = "/docs-static"
DOCS_URL = "/docs"
REDOC_URL = "/redoc"
OAUTH2_REDIRECT_URL = "/docs/oauth2-redirect"
REDOC_LOGO_URL = "https://cdn.redoc.ly/redoc/logo-mini.svg"
ASSETS = ("swagger-ui-bundle.js", "swagger-ui.css", "redoc.standalone.js", "favicon.png")
SWAGGER_PARAMETERS = {
    "validatorUrl": None,  # no badge fetched from validator.swagger.io
    "deepLinking": True,
    "docExpansion": "list",
    "defaultModelsExpandDepth": 1,
    "displayRequestDuration": True,
    "tryItOutEnabled": False,
}


def asset_dir() -> Path | None:
    """The folder with the Swagger UI / ReDoc assets, or None when the package is missing."""
    try:
        import fastapi_offline
    except ImportError:
        return None
    folder = Path(fastapi_offline.__file__).parent / "static"
    return folder if all((folder / name).is_file() for name in ASSETS) else None


def install_docs(app: FastAPI) -> bool:
    """Add ``/docs``, ``/docs/oauth2-redirect`` and ``/redoc`` to an app created with
    ``docs_url=None, redoc_url=None``; True when the pages are served offline."""
    folder = asset_dir()
    openapi_url = app.openapi_url or "/openapi.json"
    csp = docs_csp if folder is not None else (lambda page, **_: page)  # CDN pages: no same-origin-only CSP
    title = app.title
    if folder is None:
        log.warning("fastapi-offline is not installed: /docs and /redoc load their scripts from a public CDN")
        js, css, favicon = ("https://cdn.jsdelivr.net/npm/swagger-ui-dist@5/swagger-ui-bundle.js",
                            "https://cdn.jsdelivr.net/npm/swagger-ui-dist@5/swagger-ui.css",
                            "https://fastapi.tiangolo.com/img/favicon.png")
        redoc_js = "https://cdn.jsdelivr.net/npm/redoc@2/bundles/redoc.standalone.js"
    else:
        # ReDoc's sidebar shows a logo from its CDN: serve the bundle with that one URL pointed home
        redoc_source = (folder / "redoc.standalone.js").read_text(encoding="utf-8").replace(
            REDOC_LOGO_URL, f"{STATIC_URL}/favicon.png")

        @app.get(f"{STATIC_URL}/redoc.standalone.js", include_in_schema=False)
        async def redoc_bundle() -> Response:
            return Response(redoc_source, media_type="text/javascript",
                            headers={"Cache-Control": "public, max-age=86400"})

        app.mount(STATIC_URL, StaticFiles(directory=str(folder)), name="docs-static")
        js, css, favicon = (f"{STATIC_URL}/swagger-ui-bundle.js", f"{STATIC_URL}/swagger-ui.css",
                            f"{STATIC_URL}/favicon.png")
        redoc_js = f"{STATIC_URL}/redoc.standalone.js"

    @app.get(DOCS_URL, include_in_schema=False)
    async def swagger_ui(request: Request) -> HTMLResponse:
        root = request.scope.get("root_path", "")
        return csp(get_swagger_ui_html(
            openapi_url=f"{root}{openapi_url}", title=f"{title} - API docs",
            swagger_js_url=_rooted(root, js), swagger_css_url=_rooted(root, css), swagger_favicon_url=_rooted(root, favicon),
            oauth2_redirect_url=f"{root}{OAUTH2_REDIRECT_URL}", swagger_ui_parameters=SWAGGER_PARAMETERS,
        ))

    @app.get(OAUTH2_REDIRECT_URL, include_in_schema=False)
    async def swagger_ui_redirect() -> HTMLResponse:
        return csp(get_swagger_ui_oauth2_redirect_html())

    @app.get(REDOC_URL, include_in_schema=False)
    async def redoc(request: Request) -> HTMLResponse:
        root = request.scope.get("root_path", "")
        return csp(get_redoc_html(openapi_url=f"{root}{openapi_url}", title=f"{title} - ReDoc",
                                       redoc_js_url=_rooted(root, redoc_js), redoc_favicon_url=_rooted(root, favicon),
                                       with_google_fonts=False), allow_eval=True)

    return folder is not None


def _rooted(root: str, url: str) -> str:
    return url if url.startswith("http") else f"{root}{url}"
