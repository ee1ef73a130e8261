from __future__ import annotations

import pytest
from tests.support.service_testkit import Server, make_example_case


@pytest.fixture(scope="session")
def example_case(tmp_path_factory):
    return make_example_case(tmp_path_factory.mktemp("case"))


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    """One server for the API tests: auth off, asked for 0.0.0.0 (must fall back to loopback), 1 worker."""
    srv = Server(tmp_path_factory.mktemp("srv") / "data", workers=1, host="0.0.0.0",
                 env={"DSAREG_MAX_UPLOAD_BYTES": str(4 * 1024 * 1024)}).start()
    yield srv
    srv.stop()
