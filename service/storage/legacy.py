"""Databases made before Alembic (no ``alembic_version`` table): recognised by their columns, never recreated.

The last release before migrations made its tables with ``create_all`` and, at start-up, added the nullable
columns earlier releases lacked. Such a database is brought to that release's schema the same way (the
tables it made only on demand are created, the nullable columns of earlier releases are added), checked
against it column by column, and then recognised as the newest revision whose columns it already has (a
revision made while databases were still unversioned says which in ``ADOPT_IF_PRESENT``). A table that
lacks a column it cannot gain is a :class:`~service.storage.schema.SchemaError`, and
nothing is changed (the caller's transaction rolls back).
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic.script import ScriptDirectory

from .schema import SchemaError, metadata

BASELINE = "0001"


def has_any_table(conn: sa.Connection) -> bool:
    """Whether the database holds any of this service's tables."""
    return bool(set(sa.inspect(conn).get_table_names()) & set(metadata.tables))


def adopt_legacy(conn: sa.Connection, scripts: ScriptDirectory) -> str:
    """Bring an unversioned database to the baseline's tables; the revision it is at (to stamp)."""
    release = scripts.get_revision(BASELINE).module
    _complete_release_tables(conn, release.release_metadata(), release.PRE_RELEASE_NULLABLE)
    reached = BASELINE
    for script in reversed(list(scripts.iterate_revisions("heads", BASELINE))):
        if not _has_columns(conn, getattr(script.module, "ADOPT_IF_PRESENT", None)):
            break
        reached = script.revision
    return reached


def _complete_release_tables(conn: sa.Connection, release: sa.MetaData, may_add: set[tuple[str, str]]) -> None:
    inspector = sa.inspect(conn)
    present = set(inspector.get_table_names())
    for table in release.sorted_tables:
        if table.name not in present:
            table.create(conn)
            continue
        have = {c["name"] for c in inspector.get_columns(table.name)}
        for column in table.columns:
            if column.name in have:
                continue
            if (table.name, column.name) not in may_add:
                raise SchemaError(f"the job database's table {table.name} lacks the column {column.name}: it was not "
                                   "made by dsareg (or by a version too old to upgrade); restore a backup or start "
                                   "from an empty database")
            kind = column.type.compile(dialect=conn.dialect)
            conn.exec_driver_sql(f'ALTER TABLE {table.name} ADD COLUMN "{column.name}" {kind}')


def _has_columns(conn: sa.Connection, wanted: dict[str, tuple[str, ...]] | None) -> bool:
    if not wanted:
        return False
    inspector = sa.inspect(conn)
    return all(set(columns) <= {c["name"] for c in inspector.get_columns(table)} for table, columns in wanted.items())
