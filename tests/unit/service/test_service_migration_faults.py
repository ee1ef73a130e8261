"""A migration whose process is frozen (SIGSTOP) and then killed (SIGKILL) half-way through a revision, on a
real SQLite file with the last release's rows: the other process starting meanwhile waits on the migration
lock (it neither migrates beside it nor fails), proceeds as soon as the holder dies, and nothing is lost or
half-applied (the killed transaction rolls back; revision 0002 runs once, whole)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import threading
import time
from pathlib import Path

import sqlalchemy as sa

from service.storage.migrate import upgrade_database
from service.storage.revisions import head
from tests.support.migration_kit import APPLIED, NEW_COLUMNS, NEW_TABLES, make_release_database, normalized, snapshot

REPO = Path(__file__).resolve().parents[3]

HOLDER = textwrap.dedent("""
    import sys, time
    from service.storage.migrate import locked, migration_engine
    engine = migration_engine(sys.argv[1])
    with locked(engine) as conn:  # revision 0002's first statement, inside the migration's transaction
        conn.exec_driver_sql("ALTER TABLE jobs ADD COLUMN case_identity TEXT")
        print("mid-write", flush=True)
        time.sleep(600)
""")


def test_a_frozen_then_killed_migration_loses_nothing_and_the_next_start_migrates_once(tmp_path):
    url = f"sqlite:///{tmp_path / 'jobs.sqlite3'}"
    engine = sa.create_engine(url, poolclass=sa.pool.NullPool)
    make_release_database(engine)
    before = snapshot(engine)
    holder = subprocess.Popen([sys.executable, "-c", HOLDER, url], cwd=REPO, stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "mid-write"
        os.kill(holder.pid, signal.SIGSTOP)  # frozen holding the write lock, mid-revision
        reports, errors = [], []

        def start() -> None:
            try:
                reports.append(upgrade_database(url))
            except Exception as exc:  # noqa: BLE001 - asserted below
                errors.append(exc)

        starter = threading.Thread(target=start)
        starter.start()
        time.sleep(2.0)
        assert starter.is_alive() and not reports and not errors  # waits on the lock: no second migration beside it
        os.kill(holder.pid, signal.SIGKILL)
        killed_at = time.monotonic()
        starter.join(30)
        assert not starter.is_alive() and not errors, errors
        assert time.monotonic() - killed_at < 10.0  # proceeds as soon as the holder is gone
    finally:
        holder.kill()
        holder.wait()
    (report,) = reports
    assert (report.adopted, report.applied, report.after) == ("0001", APPLIED, head())
    after = snapshot(engine)
    for table, rows in before.items():
        assert normalized(after[table]) == normalized([{**row, **NEW_COLUMNS.get(table, {})} for row in rows]), table
    assert set(after) == set(before) | NEW_TABLES
    assert not upgrade_database(url).changed
    engine.dispose()
