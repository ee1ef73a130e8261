"""Whose case a job is: jobs.case_identity and jobs.case_search.

``jobs.case_identity``: JSON, patient, study, series per input (never logged); ``jobs.case_search``: the
lower-case text that ``GET /v1/registrations?q=`` matches. Nullable: jobs made before have no case recorded.

Revision ID: 0002
Revises: 0001
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0002"
down_revision = "0001"
branch_labels = None
depends_on = None

ADOPT_IF_PRESENT = {"jobs": ("case_identity", "case_search")}
"""A database made before Alembic that has these columns is past this revision (made between the release and
the first migration); :mod:`service.storage.migrate` stamps it so."""


def upgrade() -> None:
    with op.batch_alter_table("jobs") as batch:
        batch.add_column(sa.Column("case_identity", sa.Text))
        batch.add_column(sa.Column("case_search", sa.Text))


def downgrade() -> None:
    with op.batch_alter_table("jobs") as batch:
        batch.drop_column("case_search")
        batch.drop_column("case_identity")
