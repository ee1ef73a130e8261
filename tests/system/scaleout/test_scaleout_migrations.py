"""Schema migrations on a real PostgreSQL (service/storage/migrate.py): a database of the last release with rows
in every table upgrades without losing any, processes starting together migrate once (advisory lock), and the
migrations build the schema the metadata declares. SQLite: tests/unit/service/test_service_migrations.py."""

from __future__ import annotations

import uuid

import pytest
import sqlalchemy as sa
from alembic import command

from service.storage.migrate import locked, migration_engine
from service.storage.revisions import alembic_config
from service.storage.schema import metadata
from tests.support.migration_kit import assert_concurrent_starts_migrate_once, assert_upgrade_loses_nothing, schema_diff


@pytest.fixture
def database(postgres_server):
    """A new, empty database on the session's PostgreSQL (dropped afterwards)."""
    server = sa.make_url(postgres_server.url)
    name = f"migrate_{uuid.uuid4().hex[:12]}"
    admin = sa.create_engine(server.set(database="postgres"), isolation_level="AUTOCOMMIT", poolclass=sa.pool.NullPool)
    with admin.connect() as conn:
        conn.exec_driver_sql(f"CREATE DATABASE {name}")
    yield server.set(database=name).render_as_string(hide_password=False)
    with admin.connect() as conn:
        conn.exec_driver_sql(f"DROP DATABASE {name} WITH (FORCE)")
    admin.dispose()


def test_a_release_database_is_upgraded_and_loses_nothing(database):
    assert_upgrade_loses_nothing(database)


def test_migrations_and_metadata_agree(database):
    engine = migration_engine(database)
    with locked(engine) as conn:
        command.upgrade(alembic_config(conn), "head")
    assert schema_diff(engine, metadata) == []
    engine.dispose()


def test_processes_starting_together_migrate_once(database):
    assert_concurrent_starts_migrate_once(database)
