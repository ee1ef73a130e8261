"""``dsareg db upgrade | current | history``: the job database's schema migrations (service/storage/migrate.py).

``upgrade`` is what every process also runs at start-up; run it by hand to upgrade before starting the new
version (after a backup: docs/operations/upgrades.md), or to see what it would do with ``current``.
"""

from __future__ import annotations

import argparse
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any


def add_db_parser(subparsers: Any) -> None:
    db = subparsers.add_parser(
        "db", help="the job database's schema: upgrade it, show its revision, list the revisions",
        description="Schema migrations of the job database (Alembic). Every dsareg process upgrades the database "
                    "at start-up; `dsareg db upgrade` does it alone. Back the database up first "
                    "(docs/operations/upgrades.md). Settings as for serve.")
    db.add_argument("action", choices=("upgrade", "current", "history"),
                    help="upgrade: migrate to this version's schema; current: the database's revision and this "
                         "version's; history: the revisions, oldest first")
    db.add_argument("--database-url", help="SQLAlchemy URL (default: the settings', SQLite in the data dir)")
    db.add_argument("--data-dir", type=Path, help="the data dir of the default SQLite database")
    db.add_argument("--config", metavar="FILE", help="service settings file (JSON or TOML), as for serve")
    db.set_defaults(func=run_db)


def run_db(args: argparse.Namespace) -> int:
    url = _database_url(args) if args.action != "history" else ""
    with _failing_as_command(url):
        return _run(args.action, url)


def migrate_at_start(url: str) -> None:
    """``dsareg serve``: migrate before the app starts, so a failure is one line, not a lifespan traceback."""
    from ..storage.migrate import upgrade_database

    with _failing_as_command(url):
        upgrade_database(url)


@contextmanager
def _failing_as_command(url: str) -> Iterator[None]:
    """A schema or connection error as the command's one-line failure (exit 1)."""
    import sqlalchemy as sa

    from ..engine_adapter import commands
    from ..storage.schema import SchemaError

    try:
        yield
    except SchemaError as exc:
        raise commands.CommandFailed(str(exc)) from None
    except (sa.exc.OperationalError, sa.exc.InterfaceError) as exc:
        reason = str(getattr(exc, "orig", None) or exc).splitlines()[0]
        raise commands.CommandFailed(f"cannot use the job database {_shown(url)}: {reason}") from None


def _run(action: str, url: str) -> int:
    from ..storage import migrate, revisions

    if action == "history":
        for script in reversed(list(revisions.scripts().walk_revisions())):
            print(f"{script.revision}  {(script.doc or '').splitlines()[0] if script.doc else ''}")
        return 0
    if action == "upgrade":
        report = migrate.upgrade_database(url)
        print(f"{_shown(url)}: {_upgrade_line(report)}")
        return 0
    found = migrate.database_revision(url)
    state = "up to date" if found == revisions.head() else "run `dsareg db upgrade`"
    print(f"{_shown(url)}: revision {found or 'none (empty, or made before migrations)'}; "
          f"this version's: {revisions.head()} ({state})")
    return 0


def _database_url(args: argparse.Namespace) -> str:
    from ..settings import load_settings

    settings = load_settings(args.config, data_dir=args.data_dir, database_url=args.database_url)
    if settings.effective_database_url.startswith("sqlite"):
        settings.storage.data_dir.mkdir(parents=True, exist_ok=True)
    return settings.effective_database_url


def _shown(url: str) -> str:
    import sqlalchemy as sa

    return sa.make_url(url).render_as_string(hide_password=True)


def _upgrade_line(report: Any) -> str:
    if report.created:
        return f"created at revision {report.after}"
    if not report.changed:
        return f"at revision {report.after}, nothing to do"
    since = f"made before migrations, recognised as {report.adopted}" if report.adopted else f"was {report.before}"
    return f"upgraded to {report.after} ({since}; ran {', '.join(report.applied) or 'no revision'})"
