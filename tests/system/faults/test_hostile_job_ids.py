"""Job ids are checked by syntax before they reach the database (service/storage/store.py ``is_job_id``,
service/api/deps.py ``owned_job``): a NUL, an over-long or a non-id string is a 404 problem+json on
every ``{job_id}`` route, on SQLite and on a real PostgreSQL (which refuses NUL in text with a
``DataError`` that used to become a 500 on 8 routes)."""

from __future__ import annotations

import pytest

from tests.support.service_testkit import Server

PROBLEM = "application/problem+json"

BAD_IDS = ["abc%00def", "%00", "a" * 65, "f" * 5000, "abc%20def", "abc;def", "%C3%A9t%C3%A9", "%FF%FE", "a'b", "a%22b",
           "..", "abc%0Adef", "abc%09def"]
ROUTES = [
    ("GET", "/v1/registrations/{id}"), ("POST", "/v1/registrations/{id}/cancel"),
    ("DELETE", "/v1/registrations/{id}"), ("GET", "/v1/registrations/{id}/result"),
    ("GET", "/v1/registrations/{id}/overlays/ap.png"), ("GET", "/v1/registrations/{id}/masks/lat.png"),
    ("GET", "/v1/registrations/{id}/animation.gif"), ("GET", "/v1/registrations/{id}/loss.png"),
    ("GET", "/v1/registrations/{id}/dicom/reg.dcm"), ("POST", "/v1/registrations/{id}/track"),
]


def _check_every_route(srv: Server) -> int:
    tried = 0
    with srv.client() as client:
        for bad in BAD_IDS:
            for method, template in ROUTES:
                path = template.replace("{id}", bad)
                kwargs = {"files": {"ap": ("a.png", b"x"), "lat": ("l.png", b"x")}} if path.endswith("/track") else {}
                response = client.request(method, path, **kwargs)
                assert response.status_code == 404, (method, path[:80], response.status_code, response.text[:300])
                assert response.headers["content-type"].startswith(PROBLEM), (method, path[:80])
                assert response.json()["status"] == 404 and "Traceback" not in response.text
                tried += 1
        assert client.get("/readyz").status_code in (200, 503)  # the store still answers
        assert client.get("/v1/registrations").status_code == 200
    return tried


@pytest.mark.parametrize("store", ["sqlite", "postgresql"])
def test_malformed_job_ids_are_404_on_every_route(store, tmp_path, request):
    env = {}
    if store == "postgresql":
        env["DSAREG_DATABASE_URL"] = request.getfixturevalue("postgres_server").url
    srv = Server(tmp_path / "data", workers=0, env=env).start()
    try:
        tried = _check_every_route(srv)
    finally:
        srv.stop()
    assert tried == len(BAD_IDS) * len(ROUTES)
    assert "DataError" not in srv.logs() and "internal error" not in srv.logs()
