"""API keys: required when configured, hashed at rest, jobs scoped to their key; wrong keys throttled per client
address (issue 43 item 3)."""

from __future__ import annotations

import hashlib
import json
import re
import time

import httpx

from tests.support.service_testkit import Server, submit


def test_api_keys_required_and_scoped(tmp_path, example_case):
    alpha, beta = "alpha-key-0123456789", "beta-key-9876543210"
    beta_hash = hashlib.sha256(beta.encode()).hexdigest()
    srv = Server(tmp_path / "data", workers=0,
                 env={"DSAREG_API_KEYS": alpha, "DSAREG_API_KEY_HASHES": json.dumps([beta_hash]),
                      "DSAREG_RETENTION_HOURS": "0.0005", "DSAREG_SWEEP_INTERVAL_SECONDS": "0.5",
                      "DSAREG_QUEUE_LIMIT": "2", "DSAREG_QUEUE_LIMIT_PER_KEY": "1"}).start()
    try:
        with srv.client() as anonymous:
            r = anonymous.get("/v1/registrations")
            assert r.status_code == 401 and r.headers["www-authenticate"].startswith("Bearer")
            assert r.headers["content-type"].startswith("application/problem+json")
            assert anonymous.get("/v1/registrations", headers={"Authorization": "Bearer wrong"}).status_code == 401
            assert anonymous.get("/healthz").status_code == 200
        with srv.client(headers={"Authorization": f"Bearer {alpha}"}) as a, \
                srv.client(headers={"Authorization": f"Bearer {beta}"}) as b:
            assert a.get("/v1/registrations").status_code == 200
            if _engine():
                job = submit(a, example_case)
                assert job.status_code == 202, job.text
                job_id = job.json()["id"]
                assert a.get(f"/v1/registrations/{job_id}").status_code == 200
                assert b.get(f"/v1/registrations/{job_id}").status_code == 404  # no existence leak
                assert b.post(f"/v1/registrations/{job_id}/cancel").status_code == 404
                assert b.delete(f"/v1/registrations/{job_id}").status_code == 404
                assert job_id not in [j["id"] for j in b.get("/v1/registrations").json()["items"]]
                # back-pressure: 1 queued job per key, 2 in all (no workers here, so they stay queued)
                too_many = submit(a, example_case, options={"starts": 1, "max_iterations": 31})
                assert too_many.status_code == 429 and int(too_many.headers["retry-after"]) > 0
                beta_job = submit(b, example_case)
                assert beta_job.status_code == 202
                full = submit(b, example_case, options={"starts": 1, "max_iterations": 32})
                assert full.status_code == 503 and int(full.headers["retry-after"]) > 0
                assert full.headers["content-type"].startswith("application/problem+json")
                # retention: finished jobs and their files disappear after the retention period (~2 s here)
                assert a.post(f"/v1/registrations/{job_id}/cancel").json()["status"] == "canceled"
                assert b.post(f"/v1/registrations/{beta_job.json()['id']}/cancel").json()["status"] == "canceled"
                deadline = time.monotonic() + 30
                while a.get(f"/v1/registrations/{job_id}").status_code != 404 and time.monotonic() < deadline:
                    time.sleep(0.5)
                assert a.get(f"/v1/registrations/{job_id}").status_code == 404
                assert b.get(f"/v1/registrations/{beta_job.json()['id']}").status_code == 404
                assert not list((srv.data_dir / "blobs").glob("??/*"))
        _wrong_keys_are_throttled(srv, alpha)  # last: it blocks the loopback address for 60 s
    finally:
        srv.stop()
    logs = srv.logs()
    assert alpha not in logs and beta not in logs
    warnings = [line for line in logs.splitlines() if "wrong API key from" in line]
    assert len(warnings) == 1 + len(GUESSES), warnings  # the one "Bearer wrong" above, then the guesses
    assert all("127.0.0.1" in line for line in warnings) and "429" in warnings[-1], warnings
    assert re.search(r"\(10 within 60 s\)", warnings[-1]), warnings[-1]
    assert not any(guess in logs for guess in GUESSES) and "Bearer" not in "\n".join(warnings)
    assert "authentication is off" not in logs


GUESSES = [f"guessed-key-{n:02d}-s3cret" for n in range(10)]


def _wrong_keys_are_throttled(srv: Server, valid: str) -> None:
    """10 wrong keys from 127.0.0.1 within 60 s: 401 each, then 429 with Retry-After for that address, its
    valid key included (the documented policy: a blocked address learns nothing about the keys it tries, until
    its oldest counted failure is 60 s old); another client address (127.0.0.2) is not blocked."""
    with srv.client() as guesser:
        codes = [guesser.get("/v1/registrations", headers={"Authorization": f"Bearer {g}"}).status_code
                 for g in GUESSES]
        blocked = guesser.get("/v1/registrations", headers={"Authorization": "Bearer one-more-guess"})
        valid_too = guesser.get("/v1/registrations", headers={"Authorization": f"Bearer {valid}"})
        no_key = guesser.get("/v1/registrations")
        health = guesser.get("/healthz")
    assert codes == [401] * len(GUESSES)
    assert blocked.status_code == 429 and 30 <= int(blocked.headers["retry-after"]) <= 60, blocked.headers
    assert blocked.headers["content-type"].startswith("application/problem+json") and "retry in" in blocked.text
    assert valid_too.status_code == 429 and int(valid_too.headers["retry-after"]) <= 60
    assert no_key.status_code == 401 and health.status_code == 200  # no key: a plain 401, not counted
    other = httpx.HTTPTransport(local_address="127.0.0.2")  # another client address on the loopback
    with srv.client(transport=other, headers={"Authorization": f"Bearer {valid}"}) as neighbour:
        assert neighbour.get("/v1/registrations").status_code == 200


def _engine() -> bool:
    """Submitting needs the engine's input loader (workers=0 here, so not the pipeline)."""
    try:
        from dsareg_engine.io.case import load_case  # noqa: F401
    except ImportError:
        return False
    return True
