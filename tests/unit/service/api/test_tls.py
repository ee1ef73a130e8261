"""The TLS recipe of docs/deployment/security.md holds (issue 43 item 3): the API served over HTTPS by uvicorn's own
TLS with the options ``dsareg serve --ssl-certfile --ssl-keyfile`` passes (:func:`service.app.tls_options`), on
loopback, with a self-signed certificate the test makes; wrong options stop the start with one line."""

from __future__ import annotations

import shutil
import ssl
import subprocess
import threading
import time

import httpx
import pytest
import uvicorn

from service.app import TlsOptionError, create_app, http_protocol, tls_options
from service.settings import load_settings
from tests.support.servers import free_port


def _self_signed(folder):
    if shutil.which("openssl") is None:
        pytest.skip("openssl is not installed: no certificate to serve HTTPS with")
    key, cert = folder / "key.pem", folder / "cert.pem"
    subprocess.run(["openssl", "req", "-x509", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:prime256v1", "-nodes",
                    "-keyout", str(key), "-out", str(cert), "-days", "1", "-subj", "/CN=127.0.0.1",
                    "-addext", "subjectAltName=IP:127.0.0.1"], check=True, capture_output=True, timeout=30)
    return key, cert


def test_the_api_answers_over_https_with_uvicorns_own_tls(tmp_path):
    key, cert = _self_signed(tmp_path)
    settings = load_settings(None, data_dir=str(tmp_path / "data"), api_keys="k-tls-test")
    port = free_port()
    server = uvicorn.Server(uvicorn.Config(create_app(settings, start_background=False), host="127.0.0.1", port=port,
                                           http=http_protocol(settings), log_level="warning", lifespan="on",
                                           **tls_options(str(cert), str(key))))
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    try:
        deadline = time.monotonic() + 30
        while not server.started and time.monotonic() < deadline and thread.is_alive():
            time.sleep(0.05)
        trusted = ssl.create_default_context(cafile=str(cert))
        with httpx.Client(base_url=f"https://127.0.0.1:{port}", verify=trusted, timeout=10) as client:
            health = client.get("/healthz")
            jobs = client.get("/v1/registrations", headers={"Authorization": "Bearer k-tls-test"})
        assert health.status_code == 200 and jobs.status_code == 200
        assert jobs.headers["cache-control"] == "no-store"
        with pytest.raises(httpx.HTTPError):  # plain HTTP to the TLS port is not answered
            httpx.get(f"http://127.0.0.1:{port}/healthz", timeout=5)
    finally:
        server.should_exit = True
        thread.join(timeout=15)


def test_wrong_tls_options_are_refused_before_serving(tmp_path):
    key, cert = _self_signed(tmp_path)
    assert tls_options(None, None) == {}
    with pytest.raises(TlsOptionError, match="go together"):
        tls_options(str(cert), None)
    with pytest.raises(TlsOptionError, match="cannot serve HTTPS with certificate"):
        tls_options(str(key), str(cert))  # swapped
