"""The revisions (Alembic orders them by ``down_revision``, not by file name: release_baseline 0001, case_identity
0002); this file makes them part of the package."""
