"""``GET /metrics`` behind ``DSAREG_METRICS_PUBLIC`` (service/api/operations.py, service/settings/): with API
keys configured it needs a valid key unless made public; without keys it is public unless turned off; what it
shows is service-wide (no key, owner, job id or raw path), whoever asks."""

from __future__ import annotations

import hashlib
import time

import pytest

from service.storage.store import JobRecord, SqlJobStore, new_job_id
from tests.support.service_testkit import Server

ALPHA, BETA = "alpha-metrics-key-0123", "beta-metrics-key-4567"


def _owner(key: str) -> str:
    return "key:" + hashlib.sha256(key.encode()).hexdigest()[:16]


def _server(tmp_path, **env: str) -> Server:
    return Server(tmp_path / "data", workers=0, env=env).start()


@pytest.mark.parametrize(("env", "anonymous", "keyed"), [
    ({"DSAREG_API_KEYS": f"{ALPHA},{BETA}"}, 401, 200),  # default with keys: a key is needed
    ({"DSAREG_API_KEYS": f"{ALPHA},{BETA}", "DSAREG_METRICS_PUBLIC": "true"}, 200, 200),
    ({}, 200, None),  # default without keys: public
    ({"DSAREG_METRICS_PUBLIC": "false"}, 403, None),  # off, and no key could open it
])
def test_metrics_access_follows_the_setting(tmp_path, env, anonymous, keyed):
    srv = _server(tmp_path, **env)
    try:
        with srv.client() as client:
            response = client.get("/metrics")
            assert response.status_code == anonymous, response.text[:300]
            if anonymous != 200:
                assert response.headers["content-type"].startswith("application/problem+json")
            else:
                assert "dsareg_jobs" in response.text
            if keyed is not None:
                assert client.get("/metrics", headers={"Authorization": "Bearer wrong-key"}).status_code == (
                    200 if anonymous == 200 else 401)
                assert client.get("/metrics", headers={"Authorization": f"Bearer {BETA}"}).status_code == keyed
    finally:
        srv.stop()


def test_metrics_hold_no_tenant_data(tmp_path):
    srv = _server(tmp_path, DSAREG_API_KEYS=f"{ALPHA},{BETA}")
    try:
        store = SqlJobStore(f"sqlite:///{srv.data_dir / 'jobs.sqlite3'}")
        now = time.time()
        ids = [new_job_id() for _ in range(3)]
        for job_id in ids:  # alpha's queued jobs, as a submission would store them
            store.create(JobRecord(id=job_id, owner=_owner(ALPHA), status="queued", created_at=now, updated_at=now,
                                   idempotency_key=f"alpha-secret-{job_id[:6]}"))
        store.dispose()
        with srv.client(headers={"Authorization": f"Bearer {ALPHA}"}) as alpha:
            for job_id in ids:
                assert alpha.get(f"/v1/registrations/{job_id}").status_code == 200
        with srv.client(headers={"Authorization": f"Bearer {BETA}"}) as beta:
            text = beta.get("/metrics").text
        assert 'dsareg_jobs{state="queued"} 3.0' in text  # the aggregate is there...
        for secret in [*ids, _owner(ALPHA), _owner(ALPHA)[4:], ALPHA, BETA, "alpha-secret"]:
            assert secret not in text, secret  # ...and nothing that tells a tenant or a job apart
        assert 'route="/v1/registrations/{job_id}"' in text  # latency by template, never by raw path
    finally:
        srv.stop()
