"""Baseline: the schema of the last release made before Alembic (round 8, commit 8a9ae79).

Every table as that release's ``create_all`` made it (store, database blobs, DICOM inbox).

Frozen: later changes are later revisions. :mod:`service.storage.migrate` also uses :func:`release_metadata`
to recognise a database that release made (no ``alembic_version`` table) and to create the tables it made
only on demand (``blob_data`` with the database blob backend, ``dimse_instances`` with the DICOM node).

Revision ID: 0001
Revises:
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0001"
down_revision = None
branch_labels = None
depends_on = None

PRE_RELEASE_NULLABLE = {("jobs", "review_decision"), ("jobs", "review"), ("job_events", "detail")}
"""Columns releases before this one lacked and this one's start-up added (``ALTER TABLE … ADD COLUMN``)."""


def _job_tables(metadata: sa.MetaData) -> None:
    sa.Table(
        "jobs", metadata,
        sa.Column("id", sa.String(32), primary_key=True),
        sa.Column("owner", sa.String(64), nullable=False),
        sa.Column("status", sa.String(16), nullable=False),
        sa.Column("created_at", sa.Float, nullable=False),
        sa.Column("updated_at", sa.Float, nullable=False),
        sa.Column("started_at", sa.Float),
        sa.Column("finished_at", sa.Float),
        sa.Column("attempts", sa.Integer, nullable=False),
        sa.Column("max_attempts", sa.Integer, nullable=False),
        sa.Column("worker_id", sa.String(96)),
        sa.Column("lease_expires_at", sa.Float),
        sa.Column("cancel_requested", sa.Boolean, nullable=False),
        sa.Column("options", sa.Text, nullable=False),
        sa.Column("geometry", sa.Text),
        sa.Column("inputs", sa.Text, nullable=False),
        sa.Column("progress", sa.Text),
        sa.Column("result", sa.Text),
        sa.Column("error", sa.Text),
        sa.Column("artifacts", sa.Text),
        sa.Column("warnings", sa.Text),
        sa.Column("idempotency_key", sa.String(255)),
        sa.Column("request_hash", sa.String(64)),
        sa.Column("input_bytes", sa.BigInteger, nullable=False),
        sa.Column("review_decision", sa.String(16)),
        sa.Column("review", sa.Text),
        sa.UniqueConstraint("owner", "idempotency_key", name="uq_jobs_owner_idempotency"),
        sa.Index("ix_jobs_status_created", "status", "created_at"),
        sa.Index("ix_jobs_created", "created_at", "id"),
    )
    sa.Table(
        "job_blobs", metadata,
        sa.Column("job_id", sa.String(32), nullable=False, index=True),
        sa.Column("sha256", sa.String(64), nullable=False, index=True),
        sa.Column("role", sa.String(32), nullable=False),
    )
    sa.Table(
        "job_events", metadata,
        sa.Column("seq", sa.Integer, primary_key=True, autoincrement=True),
        sa.Column("job_id", sa.String(32), nullable=False, index=True),
        sa.Column("at", sa.Float, nullable=False),
        sa.Column("event", sa.String(32), nullable=False),
        sa.Column("worker_id", sa.String(96)),
        sa.Column("attempt", sa.Integer),
        sa.Column("detail", sa.Text),
    )
    sa.Table(
        "workers", metadata,
        sa.Column("id", sa.String(96), primary_key=True),
        sa.Column("pid", sa.Integer),
        sa.Column("last_seen", sa.Float, nullable=False),
    )
    sa.Table(
        "store_probe", metadata,
        sa.Column("id", sa.Integer, primary_key=True),
        sa.Column("at", sa.Float, nullable=False),
    )


def _delivery_tables(metadata: sa.MetaData) -> None:
    sa.Table(
        "job_callbacks", metadata,
        sa.Column("job_id", sa.String(32), primary_key=True),
        sa.Column("url", sa.Text, nullable=False),
        sa.Column("delivery_id", sa.String(32), nullable=False),
        sa.Column("state", sa.String(16), nullable=False),
        sa.Column("attempts", sa.Integer, nullable=False),
        sa.Column("next_attempt_at", sa.Float, nullable=False),
        sa.Column("lease_until", sa.Float),
        sa.Column("last_attempt_at", sa.Float),
        sa.Column("delivered_at", sa.Float),
        sa.Column("last_status", sa.Integer),
        sa.Column("last_error", sa.Text),
        sa.Index("ix_job_callbacks_state", "state", "next_attempt_at"),
    )
    sa.Table(
        "job_previous", metadata,
        sa.Column("job_id", sa.String(32), primary_key=True),
        sa.Column("previous_id", sa.String(32), nullable=False),
    )
    sa.Table(
        "job_exports", metadata,
        sa.Column("job_id", sa.String(32), primary_key=True),
        sa.Column("target", sa.Text, nullable=False),
        sa.Column("state", sa.String(16), nullable=False),
        sa.Column("attempts", sa.Integer, nullable=False),
        sa.Column("next_attempt_at", sa.Float, nullable=False),
        sa.Column("lease_until", sa.Float),
        sa.Column("last_attempt_at", sa.Float),
        sa.Column("done_at", sa.Float),
        sa.Column("outcome", sa.Text),
        sa.Column("last_error", sa.Text),
        sa.Index("ix_job_exports_state", "state", "next_attempt_at"),
    )


def _on_demand_tables(metadata: sa.MetaData) -> None:
    sa.Table(
        "blob_data", metadata,
        sa.Column("sha256", sa.String(64), primary_key=True),
        sa.Column("size", sa.BigInteger, nullable=False),
        sa.Column("created_at", sa.Float, nullable=False),
        sa.Column("data", sa.LargeBinary, nullable=False),
    )
    sa.Table(
        "dimse_instances", metadata,
        sa.Column("sop_instance_uid", sa.String(64), primary_key=True),
        sa.Column("study_uid", sa.String(64), nullable=False, index=True),
        sa.Column("series_uid", sa.String(64), nullable=False),
        sa.Column("sop_class_uid", sa.String(64), nullable=False),
        sa.Column("sha256", sa.String(64), nullable=False),
        sa.Column("size", sa.BigInteger, nullable=False),
        sa.Column("association", sa.String(64), nullable=False, index=True),
        sa.Column("calling_ae", sa.String(16), nullable=False),
        sa.Column("state", sa.String(16), nullable=False),
        sa.Column("received_at", sa.Float, nullable=False),
        sa.Index("ix_dimse_state_study", "state", "study_uid"),
    )


def release_metadata() -> sa.MetaData:
    """The release's tables (a fresh ``MetaData`` each call)."""
    metadata = sa.MetaData()
    for add in (_job_tables, _delivery_tables, _on_demand_tables):
        add(metadata)
    return metadata


def upgrade() -> None:
    release_metadata().create_all(op.get_bind())


def downgrade() -> None:
    release_metadata().drop_all(op.get_bind())
