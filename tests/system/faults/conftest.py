"""Fault-injection suite: real servers, real processes, real SIGKILLs (see faults_kit)."""

from __future__ import annotations


import pytest

from tests.support.scaleout_kit import PostgresServer, RedisServer
from tests.support.service_testkit import make_example_case

CASE_SIZE = 64
SLOW_CASE_SIZE = 256


@pytest.fixture(scope="session")
def case(tmp_path_factory):
    return make_example_case(tmp_path_factory.mktemp("case"), CASE_SIZE)


@pytest.fixture(scope="session")
def slow_case(tmp_path_factory):
    """The same case at 256 px: a SLOW job on it runs ~4 s on one quiet thread (on the 64-px case it
    plateaus in < 1 s, and a kill aimed at it could land after it finished)."""
    return make_example_case(tmp_path_factory.mktemp("slow_case"), SLOW_CASE_SIZE)


def _clients_missing() -> bool:
    try:
        import celery  # noqa: F401
        import psycopg  # noqa: F401
    except ImportError:
        return True
    return False


@pytest.fixture(scope="module")
def redis_server():
    """A private Redis per module: the tests restart it."""
    if _clients_missing():
        pytest.skip("celery[redis] / psycopg not installed")
    try:
        server = RedisServer().start()
    except Exception as exc:  # noqa: BLE001
        pytest.skip(f"cannot start redis-server ({exc})")
    yield server
    server.stop()


@pytest.fixture(scope="module")
def postgres_server():
    """A private PostgreSQL cluster per module: the tests stop and start it."""
    if _clients_missing():
        pytest.skip("celery[redis] / psycopg not installed")
    server = PostgresServer()
    try:
        server.start()
    except Exception as exc:  # noqa: BLE001
        server.stop()
        pytest.skip(f"cannot start a PostgreSQL cluster ({exc})")
    yield server
    server.stop()
