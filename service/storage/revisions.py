"""The Alembic side of migrating the job database: the revisions of :mod:`service.storage.migrations` run or
stamped on a connection that :mod:`service.storage.migrate` holds (in its transaction, under its lock).

Imported only when a database is not at the newest revision, and by ``dsareg db`` (Alembic with Mako costs
a process about 12 MB and 0.1 CPU-s; most starts find the database up to date).
"""

from __future__ import annotations

import functools
from pathlib import Path

import sqlalchemy as sa
from alembic import command
from alembic.config import Config
from alembic.runtime.migration import MigrationContext
from alembic.script import ScriptDirectory

from .legacy import adopt_legacy, has_any_table
from .schema import SchemaError, metadata

MIGRATIONS = Path(__file__).with_name("migrations")


def alembic_config(connection: sa.Connection | None = None) -> Config:
    config = Config()
    config.set_main_option("script_location", str(MIGRATIONS))
    config.attributes["connection"] = connection
    return config


@functools.cache
def scripts() -> ScriptDirectory:
    return ScriptDirectory.from_config(alembic_config())


def head() -> str:
    return scripts().get_current_head()


def current_revision(conn: sa.Connection) -> str | None:
    return MigrationContext.configure(conn).get_current_revision()


def bring_to_head(conn: sa.Connection) -> dict:
    """Migrate the database on ``conn`` to head: ``{"before", "applied", "created", "adopted"}`` (see
    :class:`~service.storage.migrate.UpgradeReport`)."""
    found, newest = current_revision(conn), head()
    if found == newest:
        return {"before": found}
    if found is None and not has_any_table(conn):
        metadata.create_all(conn)
        MigrationContext.configure(conn).stamp(scripts(), newest)
        return {"before": None, "created": True}
    if found is not None and found not in {s.revision for s in scripts().walk_revisions()}:
        raise SchemaError(f"the job database is at revision {found}, which this dsareg does not know (its newest is "
                          f"{newest}): a newer dsareg migrated it; run that version, or restore the backup taken "
                          "before its upgrade")
    adopted = None
    if found is None:
        adopted = adopt_legacy(conn, scripts())
        MigrationContext.configure(conn).stamp(scripts(), adopted)
    applied = tuple(reversed([s.revision for s in scripts().iterate_revisions(newest, found or adopted)]))
    command.upgrade(alembic_config(conn), "head")
    return {"before": found, "applied": applied, "adopted": adopted}
