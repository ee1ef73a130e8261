"""No PHI kept in a cache (issue 43 item 4): every route of the app, enumerated from the app itself so that a
route added later cannot escape, answers with ``nosniff`` and, unless it is a PHI-free static file,
``Cache-Control: no-store``; ``/docs`` and ``/redoc`` carry a CSP that lets their offline scripts run."""

from __future__ import annotations

import asyncio
import re

import pytest
from fastapi.testclient import TestClient
from starlette.routing import Mount

from service.api.secure_headers import SecureHeadersMiddleware, is_public
from service.app import create_app
from service.settings import load_settings

KEY = "k-secure-headers-test"
JOB = "0" * 32
PHI_ROUTES = {"/v1/registrations", "/v1/registrations/{job_id}", "/v1/registrations/{job_id}/result",
              "/v1/registrations/{job_id}/overlays/{view}.png", "/v1/registrations/{job_id}/dicom/{name}",
              "/v1/registrations/{job_id}/model.json", "/v1/registrations/{job_id}/hemodynamics.{kind}"}


@pytest.fixture(scope="module")
def client(tmp_path_factory):
    settings = load_settings(None, data_dir=str(tmp_path_factory.mktemp("data")), api_keys=KEY)
    with TestClient(create_app(settings, start_background=False), raise_server_exceptions=False) as test_client:
        yield test_client


def _requests(app):
    """(template, method, concrete path) of every route and mount of the app."""
    for route in app.routes:
        template = route.path
        concrete = re.sub(r"\{job_id\}", JOB, template)
        concrete = re.sub(r"\{[^}]+\}", "x", concrete)
        if isinstance(route, Mount):
            yield template, "GET", template + "/favicon.png"
            continue
        for method in sorted(getattr(route, "methods", None) or {"GET"}):
            if method != "HEAD":
                yield template, method, concrete


def test_every_route_answers_nosniff_and_no_store_unless_static(client):
    seen, wrong = set(), []
    for template, method, path in _requests(client.app):
        if template.endswith("/events") or template == "/openapi.json":
            continue  # the event stream (no-store already; the client would wait on it); the schema (public, 1.4 s)
        seen.add(template)
        response = client.request(method, path, headers={"Authorization": f"Bearer {KEY}"})
        cache = response.headers.get("cache-control", "")
        if response.headers.get("x-content-type-options") != "nosniff" or (not is_public(path) and cache != "no-store"):
            wrong.append((method, path, response.status_code, cache))
    assert PHI_ROUTES <= seen and not any(is_public(t) for t in PHI_ROUTES)
    assert wrong == []


def test_docs_pages_have_a_csp_that_allows_their_own_scripts_only(client):
    for page in ("/docs", "/redoc"):
        response = client.get(page)
        policy = response.headers["content-security-policy"]
        assert "default-src 'self'" in policy and "frame-ancestors 'none'" in policy and "https:" not in policy
        assert "'unsafe-inline'" not in policy.split("script-src")[1].split(";")[0]
    swagger = client.get("/docs")
    assert re.search(r"script-src 'self' 'sha256-[A-Za-z0-9+/=]{44}'", swagger.headers["content-security-policy"])
    assert "max-age" in client.get("/docs-static/swagger-ui.css").headers.get("cache-control", "max-age")


def test_a_route_own_cache_header_is_replaced():
    async def inner(scope, receive, send):
        await send({"type": "http.response.start", "status": 200,
                    "headers": [(b"cache-control", b"private, max-age=86400"), (b"content-type", b"image/png")]})
        await send({"type": "http.response.body", "body": b"png"})

    sent = []

    async def send(message):
        sent.append(message)

    scope = {"type": "http", "path": "/v1/registrations/x/overlays/ap.png", "root_path": ""}
    asyncio.run(SecureHeadersMiddleware(inner)(scope, None, send))
    assert dict(sent[0]["headers"]) == {b"cache-control": b"no-store", b"content-type": b"image/png",
                                        b"x-content-type-options": b"nosniff"}
