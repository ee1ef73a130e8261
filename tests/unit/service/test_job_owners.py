"""Jobs made before API keys were turned on (owner ``anonymous``) are hidden from every key: the start log says
so, ``dsareg jobs owners`` shows them and ``dsareg jobs assign`` hands them to a key (service/storage/owners.py,
service/cli/jobs.py, service/api/lifespan.py)."""

from __future__ import annotations

import hashlib
import logging
import time
from types import SimpleNamespace

import pytest
from fastapi.security import HTTPAuthorizationCredentials
from starlette.requests import Request

from dsareg_engine.cli import main
from service.api.deps import principal
from service.api.lifespan import warn_hidden_jobs
from service.settings import ServiceSettings
from service.storage.schema import jobs
from service.storage.store import SqlJobStore

KEY = "a-key-for-the-test"
DIGEST = hashlib.sha256(KEY.encode()).hexdigest()


def _store_with(tmp_path, owners: list[tuple[str, str | None]]) -> SqlJobStore:
    store = SqlJobStore(f"sqlite:///{tmp_path / 'jobs.db'}")
    now = time.time()
    with store.writer.begin() as conn:
        for n, (owner, idempotency_key) in enumerate(owners):
            conn.execute(jobs.insert().values(id=f"job{n}", owner=owner, status="succeeded", created_at=now,
                                              updated_at=now, options="{}", inputs="[]",
                                              idempotency_key=idempotency_key))
    return store


def _owner_of_key() -> str:
    """What the API calls the owner of a request made with ``KEY``."""
    app = SimpleNamespace(state=SimpleNamespace(ctx=SimpleNamespace(settings=ServiceSettings(api_keys=[KEY]))))
    request = Request({"type": "http", "method": "GET", "path": "/v1/registrations", "headers": [], "query_string": b"",
                       "client": ("127.0.0.1", 50000), "app": app})
    return principal(request, HTTPAuthorizationCredentials(scheme="Bearer", credentials=KEY))


def test_assign_hands_the_anonymous_jobs_to_the_key_the_api_then_sees(tmp_path, monkeypatch, capsys):
    store = _store_with(tmp_path, [("anonymous", None), ("anonymous", "retry-1"), ("anonymous", "retry-2"),
                                   (_owner_of_key(), "retry-2"), ("key:0123456789abcdef", None)])
    store.dispose()
    monkeypatch.setenv("DSAREG_API_KEYS", KEY)
    data = ["--data-dir", str(tmp_path), "--database-url", f"sqlite:///{tmp_path / 'jobs.db'}"]
    assert main(["jobs", "owners", *data]) == 0
    assert "anonymous: 3 jobs" in capsys.readouterr().out
    assert main(["jobs", "assign", "--to-key-hash", DIGEST, *data]) == 0
    out = capsys.readouterr().out
    assert f"2 jobs of anonymous now owned by {_owner_of_key()}" in out and "1 kept by anonymous" in out
    store = SqlJobStore(f"sqlite:///{tmp_path / 'jobs.db'}")
    try:
        mine, _ = store.list(owner=_owner_of_key(), status=None, limit=10, cursor=None)
        assert sorted(job.id for job in mine) == ["job0", "job1", "job3"]
    finally:
        store.dispose()


@pytest.mark.parametrize("digest, why", [(KEY, "not the key"), (hashlib.sha256(b"other").hexdigest(),
                                                                 "not the digest of a configured API key")])
def test_assign_refuses_a_key_or_an_unknown_digest(tmp_path, monkeypatch, capsys, digest, why):
    monkeypatch.setenv("DSAREG_API_KEYS", KEY)
    assert main(["jobs", "assign", "--to-key-hash", digest, "--data-dir", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert "--to-key-hash" in err and why in err and "sha256sum" in err


def test_the_start_log_says_anonymous_jobs_are_hidden_and_what_to_run(tmp_path, caplog):
    store = _store_with(tmp_path, [("anonymous", None), ("anonymous", None)])
    try:
        with caplog.at_level(logging.WARNING, logger="dsareg.service"):
            warn_hidden_jobs(SimpleNamespace(store=store))
    finally:
        store.dispose()
    assert "2 job(s) made while no API keys were configured are hidden" in caplog.text
    assert "dsareg jobs assign --to-key-hash" in caplog.text
