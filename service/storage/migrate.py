"""Bring the job database to this version's schema: the Alembic revisions of :mod:`service.storage.migrations`,
run at every start-up (API, worker, DICOM listener: :class:`~service.storage.store.SqlJobStore`) and by
``dsareg db upgrade``.

All of it runs in one transaction that first takes the migration lock, so processes starting together
migrate once and the others then find the database at head:

* PostgreSQL: a transaction-level advisory lock (``pg_advisory_xact_lock``); DDL is transactional, so a
  failed revision leaves the database as it was;
* SQLite: ``BEGIN IMMEDIATE`` (the database's write lock, waited for up to ``LOCK_WAIT_S``).

A database is one of: empty (every table is created from :mod:`service.storage.schema` and stamped at head),
at a known revision (the revisions after it run), made before Alembic (no ``alembic_version`` table:
recognised by its columns, :mod:`service.storage.legacy`, then upgraded), or at a revision this version does
not know (newer software migrated it): :class:`SchemaError`, nothing is touched.

The migration runs on its own engine without the store's short statement deadlines (an ``ALTER`` on a big
table is not a 1 s statement).
"""

from __future__ import annotations

import logging
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass

import sqlalchemy as sa

_CHATTER = ("Context impl ", "Will assume ")  # alembic.runtime.migration's lines before any revision runs


def _no_alembic_chatter(record: logging.LogRecord) -> bool:
    """Drop Alembic's set-up lines at INFO (a logging filter); its "Running upgrade A -> B" lines and warnings
    pass."""
    return record.levelno > logging.INFO or not str(record.msg).startswith(_CHATTER)


def quiet_alembic_setup() -> None:
    """Alembic logs ten INFO lines at import and per migration ("setup plugin …", "Context impl SQLiteImpl.",
    "Will assume non-transactional DDL.") that tell an operator nothing: silence them unless the operator set
    Alembic's loggers, and keep the lines of the revisions that run ("Running upgrade 0001 -> 0002, …")."""
    if logging.getLogger("alembic").level != logging.NOTSET:
        return  # set by the operator (a logging configuration): theirs
    plugins = logging.getLogger("alembic.runtime.plugins")
    if plugins.level == logging.NOTSET:
        plugins.setLevel(logging.WARNING)
    migration = logging.getLogger("alembic.runtime.migration")
    if _no_alembic_chatter not in migration.filters:
        migration.addFilter(_no_alembic_chatter)


quiet_alembic_setup()

HEAD = "0003"
"""The newest revision (migrations/versions; ``tests/unit/service/test_service_migrations.py`` checks it): a
database stamped with it needs nothing, and a start-up that finds it does not load Alembic."""
PG_LOCK_KEY = 0x6473_6172_6567  # "dsareg": the advisory lock every dsareg process migrates under
LOCK_WAIT_S = 120.0


@dataclass(frozen=True)
class UpgradeReport:
    before: str | None  # the revision found (None: empty, or made before migrations)
    after: str
    applied: tuple[str, ...] = ()  # revisions run, oldest first
    created: bool = False  # an empty database: tables created at head
    adopted: str | None = None  # made before migrations: the revision it was recognised as

    @property
    def changed(self) -> bool:
        return self.created or bool(self.applied) or self.adopted is not None


def database_revision(target: sa.Engine | str) -> str | None:
    """The revision the database of ``target`` is at (None: empty, or made before migrations)."""
    engine = migration_engine(target)
    try:
        with engine.connect() as conn:
            return _stamped_revision(conn)
    finally:
        if engine is not target:
            engine.dispose()


def upgrade_database(target: sa.Engine | str) -> UpgradeReport:
    """Migrate the database of ``target`` (an engine, or a URL) to head under the migration lock."""
    engine = migration_engine(target)
    try:
        with locked(engine) as conn:
            found = _stamped_revision(conn)
            if found == HEAD:
                return UpgradeReport(found, HEAD)
            from .revisions import bring_to_head  # Alembic only when there is something to do (revisions.py)

            return UpgradeReport(after=HEAD, **bring_to_head(conn))
    finally:
        if engine is not target:
            engine.dispose()


def _stamped_revision(conn: sa.Connection) -> str | None:
    """``alembic_version``'s revision, read without Alembic (None: no such table, or empty)."""
    if not sa.inspect(conn).has_table("alembic_version"):
        return None
    return conn.exec_driver_sql("SELECT version_num FROM alembic_version").scalar()


def migration_engine(target: sa.Engine | str) -> sa.Engine:
    """An engine for migrating: the URL's own (no pool, no short deadlines); an in-memory SQLite: ``target``."""
    url = sa.make_url(target) if isinstance(target, str) else target.url
    if url.get_backend_name() == "sqlite" and url.database in (None, "", ":memory:"):
        return target if isinstance(target, sa.Engine) else sa.create_engine(url)
    if url.get_backend_name() != "sqlite":
        return sa.create_engine(url, poolclass=sa.pool.NullPool)
    engine = sa.create_engine(url, poolclass=sa.pool.NullPool, connect_args={"timeout": LOCK_WAIT_S})
    sa.event.listen(engine, "connect", _sqlite_manual_transactions)
    sa.event.listen(engine, "begin", lambda conn: conn.exec_driver_sql("BEGIN IMMEDIATE"))
    return engine


def _sqlite_manual_transactions(dbapi_conn, _record) -> None:
    dbapi_conn.isolation_level = None  # the "begin" listener says BEGIN IMMEDIATE; DDL stays in the transaction
    dbapi_conn.execute("PRAGMA journal_mode=WAL")  # as the store runs it (store.py): a new file starts so


@contextmanager
def locked(engine: sa.Engine) -> Iterator[sa.Connection]:
    """One transaction on ``engine`` holding the migration lock (committed on success, else rolled back)."""
    with engine.begin() as conn:
        if conn.dialect.name == "postgresql":
            conn.exec_driver_sql(f"SET LOCAL lock_timeout = '{int(LOCK_WAIT_S * 1000)}ms'")
            conn.execute(sa.text("SELECT pg_advisory_xact_lock(:key)"), {"key": PG_LOCK_KEY})
        yield conn
