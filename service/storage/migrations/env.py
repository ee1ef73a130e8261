"""Alembic's entry point: migrate the connection :mod:`service.storage.migrate` hands over (``connection``
attribute), inside the transaction it holds (that transaction also holds the migration lock)."""

from __future__ import annotations

import sqlalchemy as sa
from alembic import context

from service.storage.schema import metadata


def run_migrations(connection: sa.Connection) -> None:
    context.configure(connection=connection, target_metadata=metadata,
                      render_as_batch=connection.dialect.name == "sqlite", compare_type=True)
    with context.begin_transaction():
        context.run_migrations()


def run_offline() -> None:
    """``--sql``: the DDL for a database URL, printed instead of run."""
    context.configure(url=context.config.get_main_option("sqlalchemy.url"), target_metadata=metadata,
                      literal_binds=True)
    with context.begin_transaction():
        context.run_migrations()


if context.is_offline_mode():
    run_offline()
else:
    run_migrations(context.config.attributes["connection"])
