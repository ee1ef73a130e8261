"""Alembic migrations of the job database (:mod:`service.storage.schema`); run by :mod:`service.storage.migrate`.

``versions/release_baseline.py`` (revision 0001) is the schema of the last release made before Alembic; each later
revision is one change since. A change to :mod:`service.storage.schema` goes with a new revision here
(``dsareg db revision`` is not offered: write it by hand, next to the others, and run
``tests/unit/service/test_service_migrations.py``, which compares the two). SQLite alters tables in batch mode
(copy and rename), so a revision uses ``op.batch_alter_table`` for anything beyond adding a column.
"""
