"""Deadlines on every wait for the job database: a frozen, locked or unreachable database is a
fast ``OperationalError`` (the API answers 503 + Retry-After, workers retry), never a hung request.

* **SQLite**: ``busy_timeout`` (``busy_s``): a process frozen while it holds the write lock makes
  other writers fail after that long instead of the 30 s default.
* **PostgreSQL**, four bounds:

  - *connect* (``connect_s``): a frozen server accepts the TCP connection (the kernel does) and
    never answers the start-up packet; psycopg waits at least 2 s (its floor on
    ``connect_timeout``), so the attempt runs on a helper thread we stop waiting for after
    ``connect_s`` (the thread itself ends within psycopg's 2 s);
  - *server side*: ``statement_timeout`` (``statement_s``) and ``lock_timeout`` (``lock_s``) per
    session, for a live server that is slow or where a row lock is held;
  - *client side*: a server frozen by SIGSTOP (or a network dropping packets) enforces nothing,
    so every wait of psycopg on the socket has a deadline (``statement_s`` + a margin for a
    statement, ``ping_s`` for the pool's pre-ping, commit and rollback); past it the connection
    is closed and the call raises ``OperationalError`` (SQLAlchemy then discards the pool);
  - *pool* (``pool_s``): waiting for a free pooled connection.

  Statements that move a whole blob (:mod:`service.storage.dbblobs`, :func:`bulk_statements`) get ``bulk_s``
  on both sides (a 200 MB volume is not a 1 s statement); a blob's existence check does not.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass
from typing import Any

import sqlalchemy as sa

CLIENT_MARGIN_S = 0.25


@dataclass(frozen=True)
class StoreTimeouts:
    """Seconds; see the module docstring for what each bounds."""

    busy_s: float = 1.0
    connect_s: float = 1.0
    statement_s: float = 1.0
    lock_s: float = 0.5
    pool_s: float = 1.0
    ping_s: float = 0.5
    bulk_s: float = 120.0

    @classmethod
    def from_settings(cls, settings: Any) -> StoreTimeouts:
        database = settings.database
        return cls(busy_s=database.sqlite_busy_timeout_seconds, connect_s=database.db_connect_timeout_seconds,
                   statement_s=database.db_statement_timeout_seconds, lock_s=database.db_lock_timeout_seconds,
                   pool_s=database.db_pool_timeout_seconds)


def engine_kwargs(url: str, timeouts: StoreTimeouts) -> dict[str, Any]:
    """``create_engine`` keyword arguments for ``url`` under ``timeouts``."""
    if url.startswith("sqlite"):
        return {"connect_args": {"timeout": timeouts.busy_s, "check_same_thread": False}}
    return {"pool_pre_ping": True, "pool_timeout": timeouts.pool_s}


def sqlite_busy_pragma(timeouts: StoreTimeouts) -> str:
    return f"PRAGMA busy_timeout={int(timeouts.busy_s * 1000)}"


def install_postgres_deadlines(engine: sa.Engine, timeouts: StoreTimeouts) -> None:
    """Bound connect, every statement and every other socket wait of ``engine`` (psycopg 3 only)."""
    if engine.dialect.name != "postgresql" or engine.dialect.driver != "psycopg":
        return
    connection_class = _deadline_connection_class()
    server_options = (f"-c statement_timeout={int(timeouts.statement_s * 1000)} "
                      f"-c lock_timeout={int(timeouts.lock_s * 1000)}")

    @sa.event.listens_for(engine, "do_connect")
    def _connect(_dialect: Any, _record: Any, cargs: tuple, cparams: dict) -> Any:
        cparams["options"] = f"{cparams.get('options', '')} {server_options}".strip()
        cparams.setdefault("connect_timeout", 2)  # psycopg's floor: bounds the helper thread
        conn = _connect_within(timeouts.connect_s, lambda: connection_class.connect(*cargs, **cparams))
        conn.deadline_s = timeouts.ping_s
        return conn

    @sa.event.listens_for(engine, "before_cursor_execute")
    def _arm(conn: Any, _cursor: Any, _statement: Any, _params: Any, _context: Any, _many: Any) -> None:
        bulk = conn.get_execution_options().get("dsareg_bulk")
        _raw(conn).deadline_s = (timeouts.bulk_s if bulk else timeouts.statement_s) + CLIENT_MARGIN_S

    @sa.event.listens_for(engine, "after_cursor_execute")
    def _disarm(conn: Any, _cursor: Any, _statement: Any, _params: Any, _context: Any, _many: Any) -> None:
        _raw(conn).deadline_s = timeouts.ping_s


def bulk_statements(conn: Any, timeouts: StoreTimeouts | None = None) -> Any:
    """Give the rest of ``conn``'s transaction the bulk deadline (whole-blob statements)."""
    conn.execution_options(dsareg_bulk=True)
    if conn.dialect.name == "postgresql":
        bulk_ms = int((timeouts or StoreTimeouts()).bulk_s * 1000)
        conn.exec_driver_sql(f"SET LOCAL statement_timeout = {bulk_ms}")
    return conn


def _raw(conn: Any) -> Any:
    return conn.connection.dbapi_connection


def _connect_within(seconds: float, connect: Any) -> Any:
    """``connect()`` on a helper thread; OperationalError when it has not returned after ``seconds``
    (a connection that arrives later is closed)."""
    import psycopg

    box: dict[str, Any] = {}
    lock = threading.Lock()
    done = threading.Event()

    def attempt() -> None:
        try:
            conn, error = connect(), None
        except BaseException as exc:  # noqa: BLE001 - handed to the caller
            conn, error = None, exc
        with lock:
            if box.get("abandoned"):
                if conn is not None:
                    conn.close()
                return
            box["conn"], box["error"] = conn, error
            done.set()

    threading.Thread(target=attempt, name="db-connect", daemon=True).start()
    done.wait(seconds)
    with lock:
        if not done.is_set():
            box["abandoned"] = True
            raise psycopg.OperationalError(f"no connection to the database within {seconds:g} s")
    if box["error"] is not None:
        raise box["error"]
    return box["conn"]


def _deadline_connection_class() -> type:
    import psycopg
    from psycopg import errors

    wait_timeout = getattr(errors, "_WaitTimeout", ())

    class DeadlineConnection(psycopg.Connection):
        """A psycopg connection whose every wait on the socket ends by ``deadline_s``."""

        deadline_s: float | None = None

        def wait(self, gen: Any, interval: float = 0.1, timeout: float | None = None) -> Any:
            limit = self.deadline_s if timeout is None else timeout
            try:
                return super().wait(gen, interval=interval, timeout=limit)
            except wait_timeout:
                self.close()  # mid-protocol: unusable; closed, so SQLAlchemy sees a disconnect
                raise psycopg.OperationalError(f"no answer from the database within {limit:g} s") from None

    return DeadlineConnection
