"""The job database's tables: one SQLAlchemy ``MetaData`` for everything the service keeps in it.

Jobs and their leases (``jobs``, ``job_blobs``, ``workers``), reviews and audit (columns of ``jobs``,
``job_events``), completion callbacks and PACS exports (``job_callbacks``, ``job_exports``), tracking links
(``job_previous``), blobs kept in the database (``blob_data``, :mod:`service.storage.dbblobs`), the DICOM node's
inbox (``dimse_instances``, :mod:`service.storage.inbox`) and the readiness probe (``store_probe``).

This module is the schema of the newest migration (:mod:`service.storage.migrations`): a change here goes with a
revision there, and ``tests/unit/service/test_service_migrations.py`` fails while the two disagree. Times are
epoch seconds (``Float``); JSON documents are ``Text``.
"""

from __future__ import annotations

import sqlalchemy as sa

metadata = sa.MetaData()


class SchemaError(RuntimeError):
    """The database cannot be brought to this version's schema (the message says why, and what to do)."""


jobs = sa.Table(
    "jobs", metadata,
    sa.Column("id", sa.String(32), primary_key=True),
    sa.Column("owner", sa.String(64), nullable=False),
    sa.Column("status", sa.String(16), nullable=False),
    sa.Column("created_at", sa.Float, nullable=False),
    sa.Column("updated_at", sa.Float, nullable=False),
    sa.Column("started_at", sa.Float),
    sa.Column("finished_at", sa.Float),
    sa.Column("attempts", sa.Integer, nullable=False, default=0),
    sa.Column("max_attempts", sa.Integer, nullable=False, default=3),
    sa.Column("worker_id", sa.String(96)),
    sa.Column("lease_expires_at", sa.Float),
    sa.Column("cancel_requested", sa.Boolean, nullable=False, default=False),
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
    sa.Column("input_bytes", sa.BigInteger, nullable=False, default=0),
    sa.Column("review_decision", sa.String(16)),  # the latest review's (``list(review=…)`` filters on it)
    sa.Column("review", sa.Text),  # JSON: the latest review {"decision", "comment", "by", "at"}
    sa.Column("case_identity", sa.Text),  # JSON: patient, study, series per input (never logged); revision 0002
    sa.Column("case_search", sa.Text),  # lower-case text ?q= searches (patient ID and name, study); revision 0002
    sa.UniqueConstraint("owner", "idempotency_key", name="uq_jobs_owner_idempotency"),
    sa.Index("ix_jobs_status_created", "status", "created_at"),
    sa.Index("ix_jobs_created", "created_at", "id"),
)

job_blobs = sa.Table(
    "job_blobs", metadata,
    sa.Column("job_id", sa.String(32), nullable=False, index=True),
    sa.Column("sha256", sa.String(64), nullable=False, index=True),
    sa.Column("role", sa.String(32), nullable=False),
)

job_events = sa.Table(
    "job_events", metadata,
    sa.Column("seq", sa.Integer, primary_key=True, autoincrement=True),
    sa.Column("job_id", sa.String(32), nullable=False, index=True),
    sa.Column("at", sa.Float, nullable=False),
    sa.Column("event", sa.String(32), nullable=False),
    sa.Column("worker_id", sa.String(96)),
    sa.Column("attempt", sa.Integer),
    sa.Column("detail", sa.Text),  # JSON, e.g. a review's decision and reviewer
)
"""The audit log: one row per transition of a job."""

workers = sa.Table(
    "workers", metadata,
    sa.Column("id", sa.String(96), primary_key=True),
    sa.Column("pid", sa.Integer),
    sa.Column("last_seen", sa.Float, nullable=False),
)

job_callbacks = sa.Table(
    "job_callbacks", metadata,
    sa.Column("job_id", sa.String(32), primary_key=True),
    sa.Column("url", sa.Text, nullable=False),
    sa.Column("delivery_id", sa.String(32), nullable=False),
    sa.Column("state", sa.String(16), nullable=False),  # pending | delivering | delivered | failed
    sa.Column("attempts", sa.Integer, nullable=False, default=0),
    sa.Column("next_attempt_at", sa.Float, nullable=False, default=0.0),
    sa.Column("lease_until", sa.Float),
    sa.Column("last_attempt_at", sa.Float),
    sa.Column("delivered_at", sa.Float),
    sa.Column("last_status", sa.Integer),
    sa.Column("last_error", sa.Text),
    sa.Index("ix_job_callbacks_state", "state", "next_attempt_at"),
)
"""One row per job with a ``callback_url``."""

job_previous = sa.Table(
    "job_previous", metadata,
    sa.Column("job_id", sa.String(32), primary_key=True),
    sa.Column("previous_id", sa.String(32), nullable=False),
)
"""The job a tracking job started from (``Link: rel="previous"``)."""

job_exports = sa.Table(
    "job_exports", metadata,
    sa.Column("job_id", sa.String(32), primary_key=True),
    sa.Column("target", sa.Text, nullable=False),  # JSON: {"via": "stow-rs", "server", "study_uid"} | {"via": "c-store", "peers"}
    sa.Column("state", sa.String(16), nullable=False),  # EXPORT_STATES
    sa.Column("attempts", sa.Integer, nullable=False, default=0),
    sa.Column("next_attempt_at", sa.Float, nullable=False, default=0.0),
    sa.Column("lease_until", sa.Float),
    sa.Column("last_attempt_at", sa.Float),
    sa.Column("done_at", sa.Float),
    sa.Column("outcome", sa.Text),  # JSON: what was stored
    sa.Column("last_error", sa.Text),  # JSON: the pacs-error problem of the last failed attempt
    sa.Index("ix_job_exports_state", "state", "next_attempt_at"),
)
"""One row per succeeded job that stores results into a PACS: due at once, or held for a review (``export_after_review``)."""

probe = sa.Table(
    "store_probe", metadata,
    sa.Column("id", sa.Integer, primary_key=True),
    sa.Column("at", sa.Float, nullable=False),
)
"""One row rewritten by the readiness probe (``ping``: the store accepts a write)."""

blob_data = sa.Table(
    "blob_data", metadata,
    sa.Column("sha256", sa.String(64), primary_key=True),
    sa.Column("size", sa.BigInteger, nullable=False),
    sa.Column("created_at", sa.Float, nullable=False),
    sa.Column("data", sa.LargeBinary, nullable=False),
)
"""Inputs and artifacts when ``blob_backend`` is ``database`` (scale-out without a shared filesystem)."""

volume_models = sa.Table(
    "volume_models", metadata,
    sa.Column("model_key", sa.String(64), primary_key=True),
    sa.Column("size", sa.BigInteger, nullable=False),
    sa.Column("used_at", sa.Float, nullable=False),
    sa.Column("data", sa.LargeBinary, nullable=False),
)
"""Vessel models read from volumes (``engine.model_key`` → the model file's bytes), shared by the nodes of a
deployment with the database blob backend (:mod:`service.storage.shared_models`); no patient data."""

dimse_instances = sa.Table(
    "dimse_instances", metadata,
    sa.Column("sop_instance_uid", sa.String(64), primary_key=True),
    sa.Column("study_uid", sa.String(64), nullable=False, index=True),
    sa.Column("series_uid", sa.String(64), nullable=False),
    sa.Column("sop_class_uid", sa.String(64), nullable=False),
    sa.Column("sha256", sa.String(64), nullable=False),
    sa.Column("size", sa.BigInteger, nullable=False),
    sa.Column("association", sa.String(64), nullable=False, index=True),
    sa.Column("calling_ae", sa.String(16), nullable=False),
    sa.Column("state", sa.String(16), nullable=False),  # received | interrupted | committed | dispatched | retrieving | retrieved | purging
    sa.Column("received_at", sa.Float, nullable=False),
    sa.Index("ix_dimse_state_study", "state", "study_uid"),
)
"""The DICOM node's durable index of received instances (states: :mod:`service.storage.inbox`)."""
