"""The connection to the job database every storage concern shares: one engine (one pool) for reads and a
``writer`` view of it for writes.

SQLite runs in WAL mode (readers never wait for the writer) and a write transaction takes the database lock up
front (``BEGIN IMMEDIATE``), which keeps the conditional updates of the lease protocol serialized without
deadlock retries; any other database (PostgreSQL) needs only portable SQL. Waits are bounded
(:mod:`service.storage.dbtimeouts`).
"""

from __future__ import annotations

import time
from typing import Any

import sqlalchemy as sa

from .dbtimeouts import StoreTimeouts, engine_kwargs, install_postgres_deadlines, sqlite_busy_pragma
from .schema import probe


class Database:
    """``engine`` for reads, ``writer`` (the same pool) for writes."""

    def __init__(self, url: str, timeouts: StoreTimeouts | None = None):
        self.url = url
        self.is_sqlite = url.startswith("sqlite")
        self.timeouts = timeouts or StoreTimeouts()
        self.engine = sa.create_engine(url, future=True, **engine_kwargs(url, self.timeouts))
        install_postgres_deadlines(self.engine, self.timeouts)
        if self.is_sqlite:
            busy = sqlite_busy_pragma(self.timeouts)
            sa.event.listen(self.engine, "connect", lambda dbapi_conn, record: _sqlite_pragmas(dbapi_conn, record, busy))
            sa.event.listen(self.engine, "begin", _sqlite_begin)
        self.writer = self.engine.execution_options(dsareg_write=True)

    def dispose(self) -> None:
        self.engine.dispose()

    def ping(self) -> bool:
        """True when the database accepts a write (readiness)."""
        try:
            with self.writer.begin() as conn:
                n = conn.execute(probe.update().where(probe.c.id == 1).values(at=time.time())).rowcount
                if not n:
                    conn.execute(probe.insert().values(id=1, at=time.time()))
            return True
        except Exception:  # noqa: BLE001 - readiness must answer, not raise
            return False


class OnDatabase:
    """A storage concern's implementation: it reads through ``engine`` and writes through ``writer``."""

    def __init__(self, database: Database):
        self.database = database
        self.engine, self.writer = database.engine, database.writer


def _sqlite_begin(conn: Any) -> None:
    conn.exec_driver_sql("BEGIN IMMEDIATE" if conn.get_execution_options().get("dsareg_write") else "BEGIN")


def _sqlite_pragmas(dbapi_conn: Any, _record: Any, busy_pragma: str) -> None:
    # let SQLAlchemy's "begin" event issue BEGIN IMMEDIATE itself
    dbapi_conn.isolation_level = None
    cur = dbapi_conn.cursor()
    cur.execute("PRAGMA journal_mode=WAL")
    cur.execute("PRAGMA synchronous=NORMAL")
    cur.execute(busy_pragma)  # short: a writer frozen with the lock must not hang requests (dbtimeouts)
    cur.execute("PRAGMA foreign_keys=ON")
    cur.close()


def store_outage_errors() -> tuple[type[BaseException], ...]:
    """Exceptions meaning "the job database is unreachable or busy" (connection refused or lost, pool
    timeout, SQLite locked): answered 503 by the API, retried by workers; not bugs."""
    return (sa.exc.OperationalError, sa.exc.InterfaceError, sa.exc.TimeoutError)
