"""Schema migrations (service/storage/migrate.py, legacy.py, migrations/) on SQLite; the same on PostgreSQL:
tests/system/scaleout/test_scaleout_migrations.py."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
import sqlalchemy as sa
from alembic import command

from service.storage.migrate import HEAD, locked, migration_engine, upgrade_database
from service.storage.revisions import alembic_config, head
from service.storage.schema import SchemaError, metadata
from tests.support.migration_kit import (
    APPLIED,
    assert_concurrent_starts_migrate_once,
    assert_upgrade_loses_nothing,
    make_release_database,
    schema_diff,
    snapshot,
)
from tests.support.release_schema import release_statements


def _url(tmp_path, name: str = "jobs.sqlite3") -> str:
    return f"sqlite:///{tmp_path / name}"


def _migrate_to(url: str, revision: str) -> None:
    engine = migration_engine(url)
    with locked(engine) as conn:
        command.upgrade(alembic_config(conn), revision)
    engine.dispose()


def _shape(url: str) -> dict:
    """Tables, columns (type, nullable), primary keys, unique constraints and indexes, as reflected."""
    engine = sa.create_engine(url)
    inspector = sa.inspect(engine)
    shape = {name: ([(c["name"], str(c["type"]), c["nullable"]) for c in inspector.get_columns(name)],
                    inspector.get_pk_constraint(name)["constrained_columns"],
                    sorted((u["name"], tuple(u["column_names"])) for u in inspector.get_unique_constraints(name)),
                    sorted((i["name"], tuple(i["column_names"]), bool(i["unique"])) for i in inspector.get_indexes(name)))
             for name in inspector.get_table_names() if name != "alembic_version"}
    engine.dispose()
    return shape


def test_a_release_database_is_upgraded_and_loses_nothing(tmp_path):
    assert_upgrade_loses_nothing(_url(tmp_path))


def test_the_baseline_revision_is_the_release_schema(tmp_path):
    release, migrated = _url(tmp_path, "release.sqlite3"), _url(tmp_path, "migrated.sqlite3")
    engine = sa.create_engine(release)
    with engine.begin() as conn:
        for statement in release_statements("sqlite"):
            conn.exec_driver_sql(statement)
    engine.dispose()
    _migrate_to(migrated, "0001")
    assert _shape(migrated) == _shape(release) and len(_shape(release)) == 10


def test_the_head_constant_is_the_newest_revision():
    assert HEAD == head()


def test_migrations_and_metadata_agree(tmp_path):
    by_revisions, created = _url(tmp_path, "revisions.sqlite3"), _url(tmp_path, "created.sqlite3")
    _migrate_to(by_revisions, "head")
    report = upgrade_database(created)  # empty: created from the metadata, stamped at head
    assert report.created and report.after == head()
    for url in (by_revisions, created):
        assert schema_diff(sa.create_engine(url), metadata) == [], url
    assert _shape(by_revisions) == _shape(created)


def test_processes_starting_together_migrate_once(tmp_path):
    assert_concurrent_starts_migrate_once(_url(tmp_path))


def test_a_database_of_a_newer_version_is_refused_untouched(tmp_path):
    url = _url(tmp_path)
    upgrade_database(url)
    engine = sa.create_engine(url)
    with engine.begin() as conn:
        conn.exec_driver_sql("UPDATE alembic_version SET version_num = '9999'")
    with pytest.raises(SchemaError, match="revision 9999, which this dsareg does not know"):
        upgrade_database(url)
    with engine.connect() as conn:
        assert conn.exec_driver_sql("SELECT version_num FROM alembic_version").scalar_one() == "9999"


def test_an_unversioned_database_lacking_a_release_column_is_refused_untouched(tmp_path):
    url = _url(tmp_path)
    engine = sa.create_engine(url)
    make_release_database(engine)
    with engine.begin() as conn:
        conn.exec_driver_sql("ALTER TABLE workers DROP COLUMN pid")
    before = snapshot(engine)
    with pytest.raises(SchemaError, match="workers lacks the column pid"):
        upgrade_database(url)
    assert snapshot(engine) == before and "alembic_version" not in sa.inspect(engine).get_table_names()


def test_a_database_older_than_the_release_gains_its_nullable_columns(tmp_path):
    url = _url(tmp_path)
    engine = sa.create_engine(url)
    make_release_database(engine)
    with engine.begin() as conn:  # as releases before reviews made it
        for table, column in (("jobs", "review_decision"), ("jobs", "review"), ("job_events", "detail")):
            conn.exec_driver_sql(f"ALTER TABLE {table} DROP COLUMN {column}")
        conn.exec_driver_sql("DROP TABLE blob_data")  # made only with the database blob backend
    report = upgrade_database(url)
    assert report.adopted == "0001" and report.applied == APPLIED and schema_diff(engine, metadata) == []
    assert snapshot(engine)["blob_data"] == []


def test_an_unversioned_database_made_after_the_release_is_recognised_past_it(tmp_path):
    url = _url(tmp_path)
    engine = sa.create_engine(url)
    make_release_database(engine)
    with engine.begin() as conn:  # main between the release and the first migration added the case columns
        conn.exec_driver_sql("ALTER TABLE jobs ADD COLUMN case_identity TEXT")
        conn.exec_driver_sql("ALTER TABLE jobs ADD COLUMN case_search TEXT")
    report = upgrade_database(url)
    assert (report.adopted, report.applied) == ("0002", ("0003",)) and schema_diff(engine, metadata) == []


def test_a_start_at_head_does_not_load_alembic(tmp_path):
    """The common start-up (database up to date) reads alembic_version by itself: no Alembic, no Mako."""
    url = _url(tmp_path)
    upgrade_database(url)
    code = ("import sys\nfrom service.storage.store import SqlJobStore\n"
            f"SqlJobStore({url!r}).dispose()\nprint(sorted(m for m in ('alembic', 'mako') if m in sys.modules))")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60, check=True,
                          cwd=Path(__file__).resolve().parents[3])
    assert done.stdout.strip() == "[]", done.stderr[-2000:]


def test_a_fresh_database_is_made_without_alembic_info_lines(tmp_path):
    """``dsareg serve`` on a fresh data dir logged ten Alembic INFO lines (plugins set up at import, "Context
    impl …") that tell an operator nothing; a fresh interpreter, as a start has, with INFO logging on."""
    code = ("import logging, sys\nlogging.basicConfig(level=logging.INFO)\n"
            "from service.storage.migrate import upgrade_database\n"
            "assert upgrade_database(sys.argv[1]).created\n")
    done = subprocess.run([sys.executable, "-c", code, f"sqlite:///{tmp_path / 'jobs.db'}"], capture_output=True,
                          text=True, timeout=60, cwd=Path(__file__).resolve().parents[3], check=False)
    assert done.returncode == 0, done.stderr
    assert "alembic" not in done.stderr, done.stderr


def test_an_upgrade_logs_the_revisions_it_runs_and_no_alembic_set_up_lines(tmp_path):
    """Alembic's set-up lines ("setup plugin …", "Context impl …", "Will assume …") are silenced at INFO; the
    lines of the revisions that run are kept (an operator sees what a start-up changed)."""
    code = ("import logging, sys\nlogging.basicConfig(level=logging.INFO)\n"
            "from service.storage.migrate import upgrade_database\n"
            "import sqlalchemy as sa\nfrom alembic import command\n"
            "from service.storage.revisions import alembic_config\n"
            "with sa.create_engine(sys.argv[1]).begin() as conn:\n"
            "    command.upgrade(alembic_config(conn), '0001')\n"
            "assert upgrade_database(sys.argv[1]).applied == ('0002', '0003')\n")
    done = subprocess.run([sys.executable, "-c", code, f"sqlite:///{tmp_path / 'jobs.db'}"], capture_output=True,
                          text=True, timeout=60, cwd=Path(__file__).resolve().parents[3], check=False)
    assert done.returncode == 0, done.stderr
    lines = [line for line in done.stderr.splitlines() if "alembic" in line]
    assert [line.split(",")[0] for line in lines] == ["INFO:alembic.runtime.migration:Running upgrade  -> 0001",
                                                     "INFO:alembic.runtime.migration:Running upgrade 0001 -> 0002",
                                                     "INFO:alembic.runtime.migration:Running upgrade 0002 -> 0003"]
