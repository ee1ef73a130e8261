from __future__ import annotations

import os

import pytest

from tests.support.scaleout_kit import PostgresServer, RedisServer

try:
    import celery  # noqa: F401
    import psycopg  # noqa: F401

    HAVE_CLIENTS = True
except ImportError:
    HAVE_CLIENTS = False


class External:
    """A server given by URL (cannot be restarted by the tests)."""

    def __init__(self, url: str):
        self.url = url

    def stop(self) -> None:
        pass


@pytest.fixture(scope="session")
def redis_server():
    if not HAVE_CLIENTS:
        pytest.skip("celery[redis] / psycopg not installed (pip install -e '.[test]')")
    if os.environ.get("DSAREG_TEST_REDIS_URL"):
        yield External(os.environ["DSAREG_TEST_REDIS_URL"])
        return
    try:
        server = RedisServer().start()
    except Exception as exc:  # noqa: BLE001
        pytest.skip(f"cannot start redis-server ({exc}); install it (apt-get install redis-server) "
                    "or set DSAREG_TEST_REDIS_URL")
    yield server
    server.stop()


@pytest.fixture(scope="session")
def postgres_server():
    if not HAVE_CLIENTS:
        pytest.skip("celery[redis] / psycopg not installed (pip install -e '.[test]')")
    if os.environ.get("DSAREG_TEST_DATABASE_URL"):
        yield External(os.environ["DSAREG_TEST_DATABASE_URL"])
        return
    server = PostgresServer()
    try:
        server.start()
    except Exception as exc:  # noqa: BLE001
        server.stop()
        pytest.skip(f"cannot start a PostgreSQL cluster ({exc}); install it (apt-get install postgresql) "
                    "or set DSAREG_TEST_DATABASE_URL")
    yield server
    server.stop()
