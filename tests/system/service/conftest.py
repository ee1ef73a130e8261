from __future__ import annotations

import json

import pytest
from tests.support.service_testkit import Server, make_example_case


@pytest.fixture(scope="session")
def example_case(tmp_path_factory):
    return make_example_case(tmp_path_factory.mktemp("case"))


UPLOAD_LIMIT_BYTES = 16 * 1024 * 1024  # the shared server's: a CTA series fits (volumes), a stream past it is cut (api)


@pytest.fixture(scope="session")
def server(tmp_path_factory):
    """One server for the API tests: auth off, asked for 0.0.0.0 (must fall back to loopback), 1 worker, progress
    written at every iteration (ux: a monotone progress over many polls). Shared by every module that asks for it
    (api, geometry, native_xa, track, ux, volumes: each warmed-up start costs 10–20 CPU-s); none of them needs an
    empty store, and each looks only at the jobs it submitted. Started with the fault tests' 240 s start-up wait:
    a failed start errors every test of those modules, and on a loaded 2-core machine (load 25) the warm-up took
    more than the default 90 s. Under `pytest -n 2 --dist loadfile` each process that runs one of them starts one."""
    srv = Server(tmp_path_factory.mktemp("srv") / "data", workers=1, host="0.0.0.0",
                 env={"DSAREG_MAX_UPLOAD_BYTES": str(UPLOAD_LIMIT_BYTES),
                      "DSAREG_PROGRESS_INTERVAL_SECONDS": "0"}).start(timeout=240)
    yield srv
    srv.stop()


ALPHA, BETA = "review-alpha-key-0123456789", "review-beta-key-9876543210"


@pytest.fixture(scope="session")
def keyed_server(tmp_path_factory):
    """One server with two API keys for the review tests (test_service_review*.py): 1 worker."""
    srv = Server(tmp_path_factory.mktemp("review") / "data", workers=1,
                 env={"DSAREG_API_KEYS": json.dumps([ALPHA, BETA])}).start(timeout=240)
    yield srv
    srv.stop()
