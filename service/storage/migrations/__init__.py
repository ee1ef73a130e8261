"""Alembic migrations of the job database (:mod:`service.storage.schema`); run by :mod:`service.storage.migrate`.

``versions/release_baseline.py`` (revision 0001) is the schema of the last release made before Alembic; each
later revision is one change since. A change to :mod:`service.storage.schema` goes with a new revision here
and a new ``HEAD`` in :mod:`service.storage.migrate` (written by hand, next to the others; there is no
``dsareg db revision``); ``tests/unit/service/test_service_migrations.py`` fails until the three agree. SQLite
alters tables in batch mode (copy and rename), so a revision uses ``op.batch_alter_table`` for anything beyond
adding a column.
"""
